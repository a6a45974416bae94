"""Words and units a person reads: durations, error terms, model features and diagnosis findings.

Inside the code lengths are mm and angles rad; people read micrometres (µm) and microradians
(µrad), campaign time in h:mm:ss, and "lag of T4, tau 15 min" rather than ``lag_T4``.
"""

from __future__ import annotations

import math
import re
from typing import Any

from driftlab.vocabulary import ROTATIONS as ANGLES

TERM_WORDS = {
    "dx": "translation along X",
    "dy": "translation along Y",
    "dz": "translation along Z",
    "alpha": "rotation about X",
    "beta": "rotation about Y",
    "gamma": "rotation about Z",
}
KIND_WORDS = {
    "reversal": "reversal (backlash): the error depends on the approach direction",
    "screw_expansion": "ballscrew expansion",
    "unmapped_channel": "a heat source the model's sensors do not see",
    "thermal_lag": "thermal lag",
    "sensor_fault": "faulty thermocouple",
    "drift": "slow drift",
    "quadratic": "non-linear response",
    "operating_condition": "direct effect of the machine state (spindle speed, feed)",
}


#: the units people read (the micro sign, not "u")
UM = "µm"
URAD = "µrad"
ARCSEC = "arcsec"
ARCSEC_PER_DEG = 3600.0


#: ASCII spellings of units inside the code and the modelling core's messages, and the SI symbols people read
_ASCII_UNITS = [
    (re.compile(r"(?<![A-Za-z_.])um(?:2|\^2)(?![A-Za-z_0-9])"), "µm²"),
    (re.compile(r"(?<![A-Za-z_.])um(?![A-Za-z_0-9])"), "µm"),
    (re.compile(r"(?<![A-Za-z_.])urad(?![A-Za-z_0-9])"), "µrad"),
    (re.compile(r"(?<![A-Za-z_.])degC(?:2|\^2)(?![A-Za-z_0-9])"), "°C²"),
    (re.compile(r"(?<![A-Za-z_.])degC(?![A-Za-z_0-9])"), "°C"),
]


def si_text(text: str) -> str:
    """Return ``text`` with the ASCII unit spellings (um, urad, degC, um2) as SI symbols (µm, µrad, °C, µm²).

    Only whole words are replaced: identifiers such as ``value_degC`` or ``drift_um`` stay as they are
    (``_`` before or after), so a message that names a JSON field still names it. For text a person
    reads (console lines, table cells, page text), never for JSON or data URIs.
    """
    if not text or ("um" not in text and "rad" not in text and "degC" not in text):
        return text
    for rx, symbol in _ASCII_UNITS:
        text = rx.sub(symbol, text)
    return text


def length_text(value: float, unit: str = "mm", digits: int = 2) -> str:
    """Return a small length (mm) as "12.34 µm", or a small angle (deg) as "1.23 arcsec", never in e-notation."""
    if unit == "deg":
        return f"{value * ARCSEC_PER_DEG:.{digits}f} {ARCSEC}"
    return f"{value * 1e3:.{digits}f} {UM}"


def display_unit(term: str) -> tuple[float, str]:
    """Return (factor from mm or rad, unit) for showing a term: µm for lengths, µrad for angles."""
    return (1e6, URAD) if term in ANGLES else (1e3, UM)


#: what one unit of each feature kind is (models.features.KINDS), for a coefficient's unit
FEATURE_UNITS = {
    "intercept": "",
    "direction": "",
    "session": "",
    "position": "mm",
    "dT": "°C",
    "lag": "°C",
    "mean": "°C",
    "gradient": "°C",
    "pos_dT": "mm °C",
    "lever": "mm °C",
    "quad": "°C²",
    "time": "day",
}


def coefficient_text(value: float, param: str, kind: str, power: int = 1, axis: str | None = None) -> str:
    """Return a model coefficient with its unit, e.g. "1.234 µm/°C" for a dz coefficient of a dT feature.

    Positions are mm, or rad for a rotary axis (``axis`` A or B), raised to the feature's ``power``."""
    factor, unit = display_unit(param)
    per = FEATURE_UNITS.get(kind, "")
    if kind == "position":
        per = ("rad" if axis in ("A", "B") else "mm") + ("" if power == 1 else "²" if power == 2 else f"^{power}")
    if kind == "lever" and power > 1:  # position^power x dT
        per = "mm" + ("²" if power == 2 else f"^{power}") + " °C"
    per = f"/({per})" if " " in per else (f"/{per}" if per else "")
    return f"{value * factor:.4g} {unit}{per}"


def term_label(axis: str | None, term: str | None) -> str:
    """Return e.g. "Z axis, dz (translation along Z)"."""
    words = TERM_WORDS.get(term or "", term or "")
    return f"{axis} axis, {term} ({words})" if axis else f"{term} ({words})"


def duration(s: float | None, clock: bool = False) -> str:
    """Return a duration in words ("12 min", "3.4 h"), or as h:mm:ss with ``clock``; "-" for None."""
    if s is None or not math.isfinite(s):
        return "-"
    if clock:
        n = int(round(abs(s)))
        return f"{'-' if s < 0 else ''}{n // 3600}:{n % 3600 // 60:02d}:{n % 60:02d}"
    if s < 90:
        return f"{s:.1f} s" if s < 10 else f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    if s < 3 * 86400:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.1f} days"


_FEATURE = [
    (re.compile(r"^lag(?P<tau>\d+(?:\.\d+)?)\[(?P<ch>[^\]]+)\]$"), "lag of {ch}, tau {tau}"),
    (re.compile(r"^lag_(?P<ch>.+)$"), "lag of {ch}"),
    (re.compile(r"^position\*dT_(?P<ch>.+)$"), "position x temperature rise of {ch}"),
    (re.compile(r"^pos\[(?P<ax>[^\]]+)\]\*dT\[(?P<ch>[^\]]+)\]$"), "{ax} position x temperature rise of {ch}"),
    (re.compile(r"^dT_(?P<ch>.+)\^2$"), "square of the temperature rise of {ch}"),
    (re.compile(r"^dT\[(?P<ch>[^\]]+)\]\^2$"), "square of the temperature rise of {ch}"),
    (re.compile(r"^dT_(?P<ch>.+)$"), "temperature rise of {ch}"),
    (re.compile(r"^dT\[(?P<ch>[^\]]+)\]$"), "temperature rise of {ch}"),
    (re.compile(r"^grad\[(?P<a>[^\]-]+)-(?P<b>[^\]]+)\]$"), "gradient {a} - {b}"),
    (re.compile(r"^mean\[(?P<st>[^\]]+)\]$"), "mean temperature of the {st}"),
    (re.compile(r"^fault_(?P<ch>.+)$"), "{ch} replaced by its virtual sensor"),
    (re.compile(r"^days\[(?P<ax>[^\]]+)\]$"), "days since start ({ax} axis)"),
    (re.compile(r"^dir\[(?P<ax>[^\]]+)\]$"), "approach direction on {ax}"),
]
_PLAIN = {
    "time_days": "days since start",
    "direction": "approach direction (+1 / -1)",
    "const": "constant",
    "position": "position",
    "intercept": "constant",
}


def feature_label(name: str, tau_s: float | None = None) -> str:
    """Return a model feature's name in words ("lag_T4" with tau 900 s -> "lag of T4, tau 15 min")."""
    if name in _PLAIN:
        return _PLAIN[name]
    for rx, fmt in _FEATURE:
        m = rx.match(name)
        if m:
            parts = m.groupdict()
            if "tau" in parts:
                parts["tau"] = duration(float(parts["tau"]))
            text = fmt.format(**{k: v.replace("_", " ") if k == "st" else v for k, v in parts.items()})
            if tau_s is not None and "tau" not in parts and name.startswith("lag"):
                text += f", tau {duration(float(tau_s))}"
            return text
    return name


def effect_label(effect: dict[str, Any]) -> str:
    """Return a finding in words, e.g. "thermal lag of T4, tau 15 min" or "faulty thermocouple T34 from 25.0 h"."""
    kind = str(effect.get("kind") or "")
    chans = ", ".join(effect.get("channels") or [])
    params = effect.get("params") or {}
    if kind == "thermal_lag":
        tau = params.get("tau_s")
        return f"thermal lag of {chans}" + (f", tau {duration(float(tau))}" if tau is not None else "")
    if kind == "sensor_fault":
        start = params.get("start_s")
        mode = params.get("mode")
        when = f" from {duration(float(start))} into the campaign" if start is not None else ""
        return f"faulty thermocouple {chans}{f' ({mode})' if mode else ''}{when}"
    if kind == "screw_expansion":
        return f"ballscrew expansion with {chans}" if chans else "ballscrew expansion"
    if kind == "unmapped_channel":
        return f"a heat source the model's sensors do not see, read by {chans}"
    if kind == "quadratic":
        return f"non-linear response to {chans}"
    if kind == "operating_condition":
        col = str(params.get("column") or "a machine-state column").replace("_", " ")
        power = params.get("power")
        return f"direct effect of {col}" + ("^2" if power == 2 else "")
    if kind == "drift":
        return "slow drift over days since start"
    if kind == "reversal":
        return "reversal (backlash): the error depends on the approach direction"
    return f"{kind} {chans}".strip()
