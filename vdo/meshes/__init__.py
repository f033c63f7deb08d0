"""The scene's parts below `vdo.scene`: meshes, regions of interest and their samples, camera hardware."""
