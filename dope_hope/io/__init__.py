"""File formats: one module per format, every reader returning metres (see ARCHITECTURE.md)."""
