"""diffcloth.surface stage."""
