"""The sky of a scene: DE421 ephemeris, the station's NRHO-like orbit, eclipses, far-body placement, the year's report."""
