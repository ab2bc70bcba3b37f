"""bigT.schedule layer (see DESIGN.md)."""
