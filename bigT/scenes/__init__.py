"""bigT.scenes layer (see DESIGN.md)."""
