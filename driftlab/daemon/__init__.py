"""The acquisition daemon: the run loop, the rig (instruments wired to a plan) and the simulated rig."""
