"""The capture files :func:`~bigT.acquisition.simulate_captures` writes: each format's
name and the suffix of its files.

Plain values in a module of their own, so that ``bigT acquire simulate --help`` lists
them without importing the simulator (numpy, scipy, the stores: ~0.5 s of a 0.1 s
help).
"""

from __future__ import annotations

#: Format name -> file suffix (png16 and png8: PNG of those bits).
FORMATS = {"png16": ".png", "png8": ".png", "tif": ".tif", "npy": ".npy"}
