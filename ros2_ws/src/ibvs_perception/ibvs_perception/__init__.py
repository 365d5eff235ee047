"""Window detection, pad (ArUco) detection and translational optical flow nodes for IBVS."""
