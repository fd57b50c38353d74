"""slam package."""
