(a short pass in the simulated controller's dialect: G90, G0/G1, F; stream it with)
(driftlab compensate examples/programs/stream_demo.nc --api URL --machine ID --port socket://...)
(machine coordinates inside the virtual machine's travel: X 0..254 Y 0..254 Z -254..0 mm, A B -45..45 deg)
G90 G0 X100 Y100 Z-50
G1 Z-71 F600
G1 X110 Y100 F2000
G1 X110 Y110 A2.5
G1 X100 Y110 A5
G1 X100 Y100 B5
G1 X120 Y105 A0 B0
G0 Z-50
M30
