"""bigT.compensation layer (see DESIGN.md)."""
