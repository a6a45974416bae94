%
O0100 (five-axis finishing pass on a mould cavity, after ch. 7.3)
(P20 mould steel, 2-flute ball nose, 10000 rpm, F2000 mm/min, 300 deg/min)
(machine coordinates, inside the virtual machine's travel: X 0..254 Y 0..254 Z -254..0 mm, A B -45..45 deg;)
(examples/machines/virtual-machine.yaml. The cavity's centre is at X127 Y127, its top at Z-150.)
N10 G90 G21 G17 G94
N20 T1 M6
N30 S10000 M3
N40 G0 X67.0 Y87.0 Z-100.0 A0.0 B0.0
(T=0)
N50 G1 Z-152.0 F600
N60 X97.0 Y87.0 A5.0 F2000 ; long move: subdivided so the correction follows the error along it
N70 X97.5 Y87.5 A5.5 B1.0
N80 X98.0 Y88.0 A6.0 B2.0
N90 X98.5 Y88.5 A6.5 B3.0
(T=1800)
N100 G91 X0.5 Y0.5 B1.0 (incremental section)
N110 X0.5 Y0.5 B1.0
N120 G90 X127.0 Y127.0 Z-152.4 A10.0 B5.0
(T=3600)
N130 X157.0 Y167.0 Z-152.0 A15.0 B10.0
N140 G0 Z-100.0
N150 X127.0 Y127.0 A0.0 B0.0
N160 M5
N170 M30
%
