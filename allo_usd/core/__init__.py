"""What every layer shares: errors, package paths, rotations, physical constants, atomic files, mask labels, size limits, seeds, the sensor's parameters."""
