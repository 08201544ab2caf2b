"""diffcloth.physics stage."""
