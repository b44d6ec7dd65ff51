"""vgpnav_env/envs."""
