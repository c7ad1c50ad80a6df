"""Dense mapping: plane-sweep stereo, PatchMatch, TSDF fusion and meshing."""
