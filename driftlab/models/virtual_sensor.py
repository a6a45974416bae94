"""Virtual sensors: each thermocouple modelled from its neighbours; faults flagged and replaced (ch. 6.6, fig. 6.9)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypedDict

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.models.features import fill_gaps

#: readings outside this range are the board's error signal for a broken lead (ch. 6.6)
PLAUSIBLE_DEGC: tuple[float, float] = (-40.0, 150.0)


class VirtualSensorRecord(TypedDict):
    """The JSON form of a :class:`VirtualSensor` stored in a model document."""

    channel: str
    neighbours: list[str]
    coef: list[float]  # intercept first
    sigma: float
    band: float


@dataclass
class VirtualSensor:
    """A linear model of one channel from its neighbours, with the band a healthy reading stays in."""

    channel: str
    neighbours: list[str]
    coef: np.ndarray  # intercept first
    sigma: float  # residual standard deviation on the training data
    band: float  # half-width of the alarm band, degC

    def estimate(self, temperatures: pd.DataFrame | Mapping[str, float]) -> np.ndarray:
        """Return the estimate of this channel from its neighbours' readings."""
        if isinstance(temperatures, Mapping):
            X = np.array([[float(temperatures[c]) for c in self.neighbours]])
        else:
            X = temperatures[self.neighbours].to_numpy(float)
        return self.coef[0] + X @ self.coef[1:]

    def to_dict(self) -> VirtualSensorRecord:
        """Return the JSON form stored in a model document."""
        return {
            "channel": self.channel,
            "neighbours": list(self.neighbours),
            "coef": [float(c) for c in self.coef],
            "sigma": self.sigma,
            "band": self.band,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VirtualSensor:
        """Rebuild a virtual sensor from its JSON form."""
        return cls(
            str(d["channel"]), list(d["neighbours"]), np.asarray(d["coef"], float), float(d["sigma"]), float(d["band"])
        )


def fit_virtual_sensors(
    temperatures: pd.DataFrame,
    channels: Sequence[str],
    *,
    n_neighbours: int = 3,
    band_sigma: float = 6.0,
    min_band_degC: float = 0.3,
) -> dict[str, VirtualSensor]:
    """Return one virtual sensor per channel, each a least-squares fit on its most correlated neighbours."""
    chans = [c for c in channels if c in temperatures.columns]
    if len(chans) < 2:
        raise ValidationError("virtual sensors need at least two channels")
    T = fill_gaps(temperatures[["time_s", *chans]])[chans].to_numpy(float)
    ok = np.all(np.isfinite(T), axis=1)
    T = T[ok]
    if T.shape[0] < 10:
        raise ValidationError("virtual sensors need at least ten complete scans")
    out: dict[str, VirtualSensor] = {}
    ones = np.ones((T.shape[0], 1))
    for j, c in enumerate(chans):
        order = _greedy_neighbours(T, j, n_neighbours)
        A = np.hstack([ones, T[:, order]])
        coef, *_ = np.linalg.lstsq(A, T[:, j], rcond=None)
        sigma = float(np.std(T[:, j] - A @ coef))
        out[c] = VirtualSensor(c, [chans[i] for i in order], coef, sigma, max(band_sigma * sigma, min_band_degC))
    return out


def _greedy_neighbours(T: np.ndarray, j: int, n: int) -> list[int]:
    """Return up to ``n`` columns of ``T`` chosen one by one to best explain column ``j``."""
    y = T[:, j] - T[:, j].mean()
    C = T - T.mean(axis=0)
    chosen: list[int] = []
    for _ in range(min(n, T.shape[1] - 1)):
        if chosen:
            Q, _ = np.linalg.qr(C[:, chosen])
            r = y - Q @ (Q.T @ y)
            Cr = C - Q @ (Q.T @ C)
        else:
            r, Cr = y, C
        norm2 = (Cr**2).sum(axis=0)
        gain = np.where(
            norm2 > 1e-9 * max(float(norm2.max()), 1e-300), (Cr.T @ r) ** 2 / np.maximum(norm2, 1e-300), -1.0
        )
        gain[[j, *chosen]] = -1.0
        k = int(np.argmax(gain))
        if gain[k] <= 1e-6 * float(r @ r) or gain[k] <= 0:
            break
        chosen.append(k)
    return chosen


class SensorFaultRecord(TypedDict):
    """The JSON form of a :class:`SensorFault`."""

    channel: str
    since_s: float
    max_deviation_degC: float
    mode: str
    message: str


@dataclass
class SensorFault:
    """A channel that left its band: which one, since when, how far; its estimate is used from then on."""

    channel: str
    since_s: float
    max_deviation_degC: float
    mode: str  # "out_of_band" (e.g. detached, reading the air) or "open" (error signal / no reading)

    def message(self) -> str:
        """Return the one-line notice for the operator."""
        return (
            f"thermocouple {self.channel} out of its band since t={self.since_s:.0f} s "
            f"({self.mode}, up to {self.max_deviation_degC:.2f} degC off): check the sensor; "
            f"its virtual estimate is used meanwhile"
        )

    def to_dict(self) -> SensorFaultRecord:
        """Return the JSON form."""
        return {
            "channel": self.channel,
            "since_s": self.since_s,
            "max_deviation_degC": self.max_deviation_degC,
            "mode": self.mode,
            "message": self.message(),
        }


@dataclass
class SensorCheck:
    """The result of checking a temperature record against its virtual sensors."""

    faults: list[SensorFault]
    corrected: pd.DataFrame
    replaced: pd.DataFrame = field(repr=False)  # bool, True where the estimate replaced the reading


def _first_persistent(flags: np.ndarray, persist: int) -> int | None:
    """Return the index where the first run of at least ``persist`` True values starts."""
    if persist <= 1:
        idx = np.flatnonzero(flags)
        return int(idx[0]) if idx.size else None
    run = np.convolve(flags.astype(int), np.ones(persist, int), mode="valid")
    idx = np.flatnonzero(run == persist)
    return int(idx[0]) if idx.size else None


def check_sensors(sensors: Mapping[str, VirtualSensor], temperatures: pd.DataFrame, *, persist: int = 5) -> SensorCheck:
    """Return the faults found and the record with each faulty channel replaced by its estimate.

    A channel is faulty from the start of the first run of ``persist`` scans outside its band (or
    without a plausible reading); it stays so until the operator clears it (ch. 6.6). Faults are
    resolved worst first, so a broken channel does not drag its neighbours' estimates with it.
    """
    corrected = temperatures.copy()
    chans = [c for c in sensors if c in corrected.columns]
    replaced = pd.DataFrame(False, index=corrected.index, columns=chans)
    t = corrected["time_s"].to_numpy(float)
    faults: list[SensorFault] = []
    for _ in range(len(chans)):
        filled = fill_gaps(corrected)
        worst: tuple[float, str, int, np.ndarray, np.ndarray] | None = None
        for c in chans:
            if any(f.channel == c for f in faults):
                continue
            s = sensors[c]
            raw = corrected[c].to_numpy(float)
            est = s.estimate(filled)
            bad_reading = ~np.isfinite(raw) | (raw < PLAUSIBLE_DEGC[0]) | (raw > PLAUSIBLE_DEGC[1])
            dev = np.where(bad_reading, np.inf, np.abs(raw - est))
            k = _first_persistent(dev > s.band, persist)
            if k is None:
                continue
            score = float(np.median(np.minimum(dev[k:], 1e6)) / s.band)
            if worst is None or score > worst[0]:
                worst = (score, c, k, est, bad_reading)
        if worst is None:
            break
        _, c, k, est, bad_reading = worst
        raw = corrected[c].to_numpy(float)
        finite = np.isfinite(raw[k:]) & ~bad_reading[k:]
        maxdev = float(np.max(np.abs(raw[k:][finite] - est[k:][finite]))) if finite.any() else float("inf")
        mode = "open" if bad_reading[k:].mean() > 0.5 else "out_of_band"
        faults.append(SensorFault(c, float(t[k]), maxdev, mode))
        new = raw.copy()
        new[k:] = est[k:]
        corrected[c] = new
        replaced.loc[replaced.index[k:], c] = True
    return SensorCheck(faults=faults, corrected=corrected, replaced=replaced)


def sensors_from_document(document: Any) -> dict[str, VirtualSensor]:
    """Return the virtual sensors stored in a model document (``virtual_sensors``)."""
    items = document.virtual_sensors if hasattr(document, "virtual_sensors") else document.get("virtual_sensors", [])
    return {d["channel"]: VirtualSensor.from_dict(d) for d in items}


def check_live(document: Any, temperatures: pd.DataFrame, *, persist: int = 5) -> SensorCheck:
    """Return the check of live readings against a model's virtual sensors (faulty channels replaced)."""
    sensors = sensors_from_document(document)
    if not sensors:
        raise ValidationError("the model document carries no virtual sensors")
    return check_sensors(sensors, temperatures, persist=persist)
