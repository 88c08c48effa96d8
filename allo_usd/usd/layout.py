"""Prim paths of the base stage and scene layers: one layout that author, read, inspect and the
Blender builder share."""

from __future__ import annotations


STATION_SUN = "/World/Sky/SunLight"     # the sun lamp that lights the station (not the bodies)
