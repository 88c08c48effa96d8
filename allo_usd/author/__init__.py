"""USD authoring (pxr only): assets, the base stage and per-scene layers."""
