"""Parameter identification from recorded runs."""
