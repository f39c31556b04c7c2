"""The PAC dataset generator's library parts (``datasets_scripts/`` holds the command-line entry points)."""
