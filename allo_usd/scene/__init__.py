"""Resolving one scene: camera rig and perturbation, ray casting, anomaly placement, the resolved SceneSpec."""
