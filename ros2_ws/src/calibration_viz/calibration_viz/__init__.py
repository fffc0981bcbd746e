"""Live 3D view of a calibration in the browser (viser): see viz_node."""
