"""Procedural and imported assets, as plain numpy meshes (see allo_usd.assets.mesh)."""
