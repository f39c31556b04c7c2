"""Everything that touches LeRobot internals or older formats: version checks, patches, old checkpoints."""
