"""Types J, K, T (and E through the same path) against NIST ITS-90 table values (NIST Monograph 175)."""

from __future__ import annotations

import numpy as np
import pytest

from driftlab.daq.thermocouple import TYPES, card_emf_to_temperature, emf_mv, temperature_c, type_e_emf_mv
from driftlab.errors import ValidationError

# NIST ITS-90 tables, reference junction at 0 degC: degC -> mV, printed to 1 uV. Both signs of
# temperature, and the ends of each inverse polynomial's range.
NIST_TABLES = {
    "J": [
        (-210, -8.095),
        (-200, -7.890),
        (-100, -4.633),
        (0, 0.0),
        (100, 5.269),
        (200, 10.779),
        (500, 27.393),
        (760, 42.919),
        (1000, 57.953),
        (1200, 69.553),
    ],
    "K": [
        (-270, -6.458),
        (-200, -5.891),
        (-100, -3.554),
        (0, 0.0),
        (25, 1.000),
        (100, 4.096),
        (200, 8.138),
        (300, 12.209),
        (500, 20.644),
        (1000, 41.276),
        (1372, 54.886),
    ],
    "T": [
        (-270, -6.258),
        (-200, -5.603),
        (-100, -3.379),
        (0, 0.0),
        (100, 4.279),
        (200, 9.288),
        (300, 14.862),
        (400, 20.872),
    ],
    "E": [(-270, -9.835), (-200, -8.825), (-100, -5.237), (0, 0.0), (100, 6.319), (500, 37.005), (1000, 76.373)],
}
CASES = [(k, t, mv) for k, rows in NIST_TABLES.items() for t, mv in rows]
UV = 1e-3  # mV


@pytest.mark.parametrize(("kind", "t_c", "mv"), CASES)
def test_forward_matches_the_nist_table_to_its_last_digit(kind, t_c, mv):
    assert abs(float(emf_mv(kind, t_c)) - mv) <= 0.5 * UV + 1e-9


@pytest.mark.parametrize(("kind", "t_c", "mv"), [c for c in CASES if c[0] != "E" or c[1] >= -200])
def test_inverse_matches_the_nist_table(kind, t_c, mv):
    if not TYPES[kind].mv_breaks[0] <= mv <= TYPES[kind].mv_breaks[-1]:
        assert np.isnan(temperature_c(kind, mv))  # below the inverse polynomial's range (e.g. K at -270 degC)
        return
    slope = float(TYPES[kind]._slope(np.array(float(t_c))))
    # the table's 1 uV rounding is worth 0.5 uV / slope degC
    assert abs(float(temperature_c(kind, mv)) - t_c) <= 0.5 * UV / slope + 1e-6


@pytest.mark.parametrize("kind", ["J", "K", "T", "E"])
def test_inverse_is_the_exact_inverse_of_the_reference_function(kind):
    lo, hi = TYPES[kind].t_breaks[0], TYPES[kind].t_breaks[-1]
    t = np.linspace(max(lo, -199.0), hi - 1.0, 700)
    back = temperature_c(kind, emf_mv(kind, t))
    assert np.abs(back - t).max() < 1e-6


def test_type_k_exponential_term_is_there_above_zero():
    # without a0 exp(a1 (t - a2)^2) the K function is off by 0.1186 mV near 127 degC
    a0, a1, a2 = TYPES["K"].exponential
    t = 126.9686
    poly = float(np.polynomial.polynomial.polyval(t, TYPES["K"].forward[1]))
    assert float(emf_mv("K", t)) - poly == pytest.approx(a0)


def test_type_e_path_unchanged_and_card_conversion_per_type():
    t = np.linspace(-150, 900, 50)
    assert np.allclose(emf_mv("E", t), type_e_emf_mv(t), rtol=0, atol=1e-12)
    cj = 23.5
    for kind in "JKT":
        hot = np.array([35.0, 80.0, -20.0])
        volts = (emf_mv(kind, hot) - emf_mv(kind, cj)) * 1e-3
        temps, open_mask = card_emf_to_temperature(volts, cj, tc_type=kind)
        assert not open_mask.any() and np.allclose(temps, hot, atol=1e-6)
        # read as the wrong type, the same volts are degrees off
        wrong, _ = card_emf_to_temperature(volts, cj, tc_type="E")
        assert np.abs(wrong - hot).max() > 1.0


def test_out_of_range_and_unknown_types():
    assert np.isnan(temperature_c("T", 25.0))
    with pytest.raises(ValidationError, match="defined for -270..400 degC"):
        emf_mv("T", 500.0)
    with pytest.raises(ValidationError, match="thermocouple type 'S' is not one of E J K T"):
        emf_mv("S", 20.0)
