"""Mesh export (OBJ). Owned by the surface stage."""

__all__: list[str] = []
