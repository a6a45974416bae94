"""NI-DAQmx analog inputs through NI's own ``nidaqmx`` package: the proximity sensors' A/D (thesis ch. 5.5, app. C).

Written from the NI-DAQmx Python API documentation (nidaqmx-python, "Task", ``ai_channels.
add_ai_voltage_chan(physical_channel, terminal_config, min_val, max_val)``, ``timing.
cfg_samp_clk_timing``, ``Task.read``, ``constants.TerminalConfiguration``, ``system.Device``) and
the NI-DAQmx Help topic "Physical Channel Syntax" (``Dev1/ai0:4``, comma-separated lists).

``read_volts(indices)`` is the interface :mod:`driftlab.daq.proximity` calibrates to distance
(appendix C: constant and slope per sensor, the reference-surface arrays of tables C.1/C.2), so an
NI card and a 34970A's DC-volt channels are interchangeable in the proximity role. Each reading
is the mean of ``samples`` hardware-timed samples at ``rate_hz`` (the thesis averages ten readings
per point, ch. 5.5), or one on-demand sample.

``nidaqmx`` is imported when a device is opened (an optional dependency: ``driftlab[nidaq]``) and
needs NI's NI-DAQmx runtime on the machine; without either, opening is one InstrumentError line.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from driftlab.errors import InstrumentError, ValidationError

TERMINALS = ("RSE", "NRSE", "DIFF", "PSEUDO_DIFF", "DEFAULT")
_CHANNEL = re.compile(r"^\s*([A-Za-z][\w]*)/ai(\d+)(?::(\d+))?\s*$")


def physical_channels(spec: str) -> tuple[str, list[str]]:
    """Return (device, each physical channel) of an NI-DAQmx channel list such as ``Dev1/ai0:4,Dev1/ai7``."""
    device: str | None = None
    out: list[str] = []
    for part in spec.split(","):
        m = _CHANNEL.match(part)
        if not m:
            raise ValidationError(f"NI-DAQmx channel {part.strip()!r}: write Dev1/ai0 or a range Dev1/ai0:4")
        dev, lo, hi = m.group(1), int(m.group(2)), int(m.group(3) or m.group(2))
        if device is not None and dev != device:
            raise ValidationError("NI-DAQmx channels of one task must be on one device")
        if hi < lo:
            raise ValidationError(f"NI-DAQmx range {part.strip()!r} runs backwards")
        device = dev
        out.extend(f"{dev}/ai{i}" for i in range(lo, hi + 1))
    if device is None or len(set(out)) != len(out):
        raise ValidationError(f"NI-DAQmx channels {spec!r}: give each channel once")
    return device, out


class NIDaqVolts:
    """Analog voltage inputs of an NI-DAQmx device, read on demand or averaged over a hardware-timed burst."""

    def __init__(
        self,
        channels: str,
        min_v: float = 0.0,
        max_v: float = 10.0,
        terminal: str = "DEFAULT",
        samples: int = 1,
        rate_hz: float = 1000.0,
    ) -> None:
        self.device, self.physical = physical_channels(channels)
        self.spec = channels
        if not min_v < max_v:
            raise ValidationError("NI-DAQmx input range: min_v must be below max_v")
        if str(terminal).upper() not in TERMINALS:
            raise ValidationError(f"NI-DAQmx terminal {terminal!r} is not one of {', '.join(TERMINALS)}")
        if samples < 1 or not rate_hz > 0:
            raise ValidationError("NI-DAQmx: samples >= 1 and a positive rate_hz")
        self.min_v, self.max_v = float(min_v), float(max_v)
        self.terminal = str(terminal).upper()
        self.samples, self.rate_hz = int(samples), float(rate_hz)
        self.n_channels = len(self.physical)
        self._task: Any | None = None
        self.idn: str | None = None

    def open(self) -> NIDaqVolts:
        """Create the task and its channels; InstrumentError (one line) without nidaqmx, the runtime or the device."""
        try:
            # optional extra (driftlab[nidaq]): imported where the task opens, so the rest runs without it
            import nidaqmx
            from nidaqmx.constants import AcquisitionType, TerminalConfiguration
        except ImportError:
            raise InstrumentError(
                "NI-DAQmx: the nidaqmx package is not installed (pip install driftlab[nidaq])"
            ) from None
        try:
            task = nidaqmx.Task()
        except nidaqmx.errors.Error as exc:
            raise InstrumentError(f"NI-DAQmx: {' '.join(str(exc).split())}") from None
        try:
            task.ai_channels.add_ai_voltage_chan(
                self.spec,
                terminal_config=TerminalConfiguration[self.terminal],
                min_val=self.min_v,
                max_val=self.max_v,
            )
            if self.samples > 1:
                task.timing.cfg_samp_clk_timing(
                    self.rate_hz, sample_mode=AcquisitionType.FINITE, samps_per_chan=self.samples
                )
            dev = nidaqmx.system.Device(self.device)
            self.idn = f"National Instruments,{dev.product_type},{dev.serial_num:X},NI-DAQmx"
        except nidaqmx.errors.Error as exc:
            task.close()
            raise InstrumentError(f"NI-DAQmx {self.spec}: {' '.join(str(exc).split())}") from None
        self._task = task
        return self

    def identify(self) -> str:
        """Return the device's product type and serial number."""
        if self._task is None:
            self.open()
        assert self.idn is not None
        return self.idn

    def read_volts(self, channels: Sequence[int]) -> np.ndarray:
        """Return the voltages (V) of channel indices ``channels`` (0 = the first of the list), each averaged."""
        idx = list(channels)
        if not idx or min(idx) < 0 or max(idx) >= self.n_channels:
            raise ValidationError(f"A/D channel indices must be 0..{self.n_channels - 1}")
        if self._task is None:
            self.open()
        # optional extra (driftlab[nidaq]): imported where the task opens, so the rest runs without it
        import nidaqmx

        try:
            data = self._task.read(number_of_samples_per_channel=self.samples)  # type: ignore[union-attr]
        except nidaqmx.errors.Error as exc:
            raise InstrumentError(f"NI-DAQmx {self.spec}: {' '.join(str(exc).split())}") from None
        volts = np.asarray(data, dtype=float).reshape(self.n_channels, -1).mean(axis=1)
        return volts[np.array(idx)]

    def close(self) -> None:
        """Release the task."""
        if self._task is not None:
            self._task.close()
            self._task = None
