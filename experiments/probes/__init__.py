"""Diagnostic probes: can the vision branch locate the goal (`vision`), can the NICOL physics be
solved by a scripted controller (`scripted`, the controller of `grasping`), are the NICOL contacts
plausible (`physics`: cube speed, height, restitution, penetration, normaliser statistics), how often
the trainer's exploration lifts the cube (`exploration`)."""
