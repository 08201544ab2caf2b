"""diffcloth.render stage."""
