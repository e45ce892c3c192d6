"""Layer 3: geometry on tensors: cameras and rays, mesh helpers, ray-cast rendering,
collision detection and the conic distance field."""
