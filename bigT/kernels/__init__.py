"""bigT.kernels layer (see DESIGN.md)."""
