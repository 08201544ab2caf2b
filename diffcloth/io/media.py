"""Images and videos (PNG, GIF, MP4) and result JSON."""

__all__: list[str] = []
