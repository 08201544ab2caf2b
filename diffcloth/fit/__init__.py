"""diffcloth.fit stage."""
