"""vgpnav_env/perception."""
