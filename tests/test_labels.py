"""Words and units a person reads: µm, µrad and arcsec, a unit beside every coefficient, no e-notation."""

from __future__ import annotations

from driftlab import labels
from driftlab.models.features import KINDS


def test_lengths_and_angles_carry_their_symbols():
    assert labels.display_unit("dz") == (1e3, "µm") and labels.display_unit("beta") == (1e6, "µrad")
    assert labels.length_text(0.0000123) == "0.01 µm" and labels.length_text(0.0123) == "12.30 µm"
    assert labels.length_text(1 / 3600, "deg") == "1.00 arcsec"


def test_every_feature_kind_gives_its_coefficient_a_unit():
    assert set(KINDS) <= set(labels.FEATURE_UNITS)
    assert labels.coefficient_text(0.0012, "dz", "dT") == "1.2 µm/°C"
    assert labels.coefficient_text(1.21e-5, "dx", "pos_dT") == "0.0121 µm/(mm °C)"
    assert labels.coefficient_text(2e-6, "alpha", "quad") == "2 µrad/°C²"
    assert labels.coefficient_text(0.004, "dz", "intercept") == "4 µm"
    assert labels.coefficient_text(-1.116e-3, "dz", "position", 2, "A") == "-1.116 µm/rad²"
    assert labels.coefficient_text(-4.686e-6, "dz", "position", 1, "Y") == "-0.004686 µm/mm"
