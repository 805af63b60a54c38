"""The physics and its inputs: spatial algebra, the robot model and the files it is read from,
kinematics, dynamics, contact, the target, the integrator, the desired trajectory, joint limits
and the float64 switch. A module here imports only modules here."""
