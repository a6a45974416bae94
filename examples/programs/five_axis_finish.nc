%
O0100 (five-axis finishing pass on a mould cavity, after ch. 7.3)
(P20 mould steel, 2-flute ball nose, 10000 rpm, F2000 mm/min, 300 deg/min)
N10 G90 G21 G17 G94
N20 T1 M6
N30 S10000 M3
N40 G0 X-60.0 Y-40.0 Z50.0 A0.0 B0.0
(T=0)
N50 G1 Z-2.0 F600
N60 X-30.0 Y-40.0 A5.0 F2000 ; long move: subdivided so the correction follows the error along it
N70 X-29.5 Y-39.5 A5.5 B1.0
N80 X-29.0 Y-39.0 A6.0 B2.0
N90 X-28.5 Y-38.5 A6.5 B3.0
(T=1800)
N100 G91 X0.5 Y0.5 B1.0 (incremental section)
N110 X0.5 Y0.5 B1.0
N120 G90 X0.0 Y0.0 Z-2.4 A10.0 B5.0
(T=3600)
N130 X30.0 Y40.0 Z-2.0 A15.0 B10.0
N140 G0 Z50.0
N150 X0.0 Y0.0 A0.0 B0.0
N160 M5
N170 M30
%
