"""bigT.algorithms layer (see DESIGN.md)."""
