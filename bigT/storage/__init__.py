"""bigT.storage layer (see DESIGN.md)."""
