"""IBVS core (frames, camera model, paper features and control laws, mode state machine) and the control nodes: mode supervisor, outer-loop force controller, MAVLink bridge."""
