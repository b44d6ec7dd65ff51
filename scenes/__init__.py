"""Scene specifications, procedural generation, meshes and MuJoCo models (vgpnav_env.scenes)."""
