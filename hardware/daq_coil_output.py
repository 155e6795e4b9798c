"""The coils' driver: commanded currents from LCM to the amplifiers' analog inputs.

A small adapter for current-mode amplifiers driven by an NI analog-output card
through ``nidaqmx``: each ``coil_currents_t`` command on the application's
channel becomes one voltage per coil, ``current / amps_per_volt``, written to
the card's channels in coil order. A command that breaks the contract (another
coil count, a non-finite or over-limit current) is never written: the outputs
go to 0 V (coils off) and the reason is returned; so does a command with the
power cut (``power_enabled`` false: wire the amplifiers' enable pins to the supply
the application cuts, since a stuck amplifier ignores 0 V). NI-DAQmx itself (the vendor's
runtime) must be installed on the machine with the card.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from maglev_haptics.hardware.extras import MissingDriverError, require_extra
from maglev_haptics.hardware.lcm_messages import coil_currents_t


@dataclass
class CoilOutputContract:
    """What the card may be asked for: ``n_coils`` currents within ``current_limit_a``
    (A), at ``amps_per_volt`` (A/V) of amplifier transconductance."""

    n_coils: int
    current_limit_a: float
    amps_per_volt: float

    def __post_init__(self):
        if not (np.isfinite(self.amps_per_volt) and self.amps_per_volt > 0):
            raise ValueError(f"amps_per_volt = {self.amps_per_volt}: must be a finite "
                             "number > 0 (A/V)")


def coil_voltages(message: coil_currents_t,
                  contract: CoilOutputContract) -> Tuple[np.ndarray, Optional[str]]:
    """(volts (n_coils,), None) for a command within the contract; else
    (zeros, why): every coil off."""
    off = np.zeros(contract.n_coils)
    if not message.power_enabled:
        return off, "the application cut the coils' power"
    if message.num_coils != contract.n_coils:
        return off, (f"command for {message.num_coils} coils: the card drives "
                     f"{contract.n_coils}")
    currents = np.asarray(message.current_a, dtype=float)
    if not np.all(np.isfinite(currents)):
        return off, "command holds a non-finite current"
    worst = float(np.max(np.abs(currents))) if currents.size else 0.0
    # A hair over from rounding is the limit; more is a broken command.
    if worst > contract.current_limit_a * (1 + 1e-9):
        return off, (f"command of {worst:.3f} A exceeds the {contract.current_limit_a} A "
                     "current limit")
    return currents / contract.amps_per_volt, None


class DaqCoilOutput:
    """Writes commanded coil currents to an NI card's analog outputs.

    ``channels`` are NI-DAQmx physical channel names in coil order
    (``["Dev1/ao0", ...]``). ``apply(message)`` writes one command and returns
    None, or why it turned the coils off instead.
    """

    def __init__(self, channels: List[str], contract: CoilOutputContract):
        nidaqmx = require_extra("nidaqmx", "The coil current output (NI DAQ)")
        if len(channels) != contract.n_coils:
            raise ValueError(f"channels has {len(channels)} entries: the contract has "
                             f"{contract.n_coils} coils")
        self._contract = contract
        try:
            self._task = nidaqmx.Task()
        except nidaqmx.errors.DaqNotFoundError:
            raise MissingDriverError(
                "The coil current output needs NI-DAQmx, National Instruments' driver, on "
                "this machine (ni.com/downloads): nidaqmx found none") from None
        limit_v = contract.current_limit_a / contract.amps_per_volt
        try:
            for name in channels:
                self._task.ao_channels.add_ao_voltage_chan(name, min_val=-limit_v,
                                                           max_val=limit_v)
        except nidaqmx.errors.DaqError as error:
            self._task.close()
            raise OSError(f"channels: NI-DAQmx refused {channels}: "
                          f"{str(error).splitlines()[0]}") from None

    def apply(self, message: coil_currents_t) -> Optional[str]:
        volts, why = coil_voltages(message, self._contract)
        self._task.write(volts.tolist(), auto_start=True)
        return why

    def serve(self, lcm, channel: str, duration_s: float, command_timeout_s: float) -> dict:
        """Apply every command on ``channel`` of ``lcm`` for ``duration_s`` s (wall
        clock), the coils off whenever the newest is older than ``command_timeout_s``
        (s: the application stopped) and at the end; {"applied", "refused",
        "timeouts"} counts."""
        counts = {"applied": 0, "refused": 0, "timeouts": 0}
        newest = [-float("inf")]  # when the newest command was applied (monotonic s)

        def apply(_, data):
            why = self.apply(coil_currents_t.decode(data))
            counts["refused" if why else "applied"] += 1
            newest[0] = time.monotonic()

        lcm.subscribe(channel, apply)
        end = time.monotonic() + duration_s
        off = True
        try:
            while time.monotonic() < end:
                lcm.handle_timeout(1)
                stale = time.monotonic() - newest[0] > command_timeout_s
                if stale and not off:
                    self._task.write([0.0] * self._contract.n_coils, auto_start=True)
                    counts["timeouts"] += 1
                off = stale
        finally:
            self.close()
        return counts

    def close(self) -> None:
        self._task.write([0.0] * self._contract.n_coils, auto_start=True)  # coils off
        self._task.close()

