"""lerobot_formation."""
