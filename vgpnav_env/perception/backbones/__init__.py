"""vgpnav_env/perception/backbones."""
