"""Seeing a run: read any USD stage's animation (`playback`), write a self-contained browser
player (`page`, ``warp-cloth view``) and ray-cast preview images and GIFs with Warp kernels
(`render`, ``warp-cloth render``)."""
