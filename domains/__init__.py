"""MJCF arms and task scenes, shipped inside the package as ``modnet.domains``."""
