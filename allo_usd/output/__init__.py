"""Files from renders: atomic PNG/EXR/mask/JSON writers, sensor noise, dataset assembly."""
