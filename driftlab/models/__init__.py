"""Pure physics and fitting: kinematics, thermal network, simulation, regression, diagnosis."""
