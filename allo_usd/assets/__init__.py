"""Procedural and imported assets, as plain numpy meshes (see allo_usd.mesh)."""
