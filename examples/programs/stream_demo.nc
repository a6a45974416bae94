(a short pass in the simulated controller's dialect: G90, G0/G1, F; stream it with)
(driftlab compensate examples/programs/stream_demo.nc --api URL --machine ID --port socket://...)
G90 G0 X0 Y0 Z20
G1 Z-1 F600
G1 X10 Y0 F2000
G1 X10 Y10 A2.5
G1 X0 Y10 A5
G1 X0 Y0 B5
G1 X20 Y5 A0 B0
G0 Z20
M30
