"""Pure physics at the bottom of driftlab: nothing here reads a file, a store or an instrument.

- ``kinematics``: the homogeneous-transformation chain of the five-axis machine (ch. 4, Table A.1),
  work-space errors from element errors, their allocation back to links, the compensation solve.
- ``thermal``: the first-order thermal network the simulator runs (ch. 5.3, Fig. 5.4), solved
  exactly per step.
- ``lag``: the first-order lag of sampled readings, the one filter every model and generator uses.

Used by the simulator (``daq.sim``), the models and the compensator alike.
"""
