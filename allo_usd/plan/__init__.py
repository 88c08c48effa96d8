"""What to make: the plan model, its scene enumeration and quotas, plan files, render settings and presets."""
