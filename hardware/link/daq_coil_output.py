"""The coils' driver: commanded currents from LCM to the amplifiers' analog inputs.

A small adapter for current-mode amplifiers driven by an NI analog-output card
through ``nidaqmx``: each ``coil_currents_t`` command on the application's
channel becomes one voltage per coil, ``current / amps_per_volt``, written to
the card's channels in coil order.

The same policy as ``maglev device-sim`` (``hardware/link/link_checks.py``,
``hardware/link/lease.py``): a command is written only if it decodes, commands the
card's coil count, holds finite currents within the limit, comes from the session
that holds the device's lease and is newer than the last one accepted. A refused
command is a lost command: it is counted and never reaches the coils, and the last
good one holds until ``command_timeout_s`` turns the coils off (0 V). A command
with the power cut (``power_enabled`` false: wire the amplifiers' enable pins to
the supply the application cuts, since a stuck amplifier ignores 0 V) is a good
command, and writes 0 V. NI-DAQmx itself (the vendor's runtime) must be installed
on the machine with the card.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, List

import numpy as np

from maglev_haptics.hardware.link.extras import MissingDriverError, require_extra
from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.link.lcm_messages import coil_currents_t, lease_t
from maglev_haptics.hardware.link.lease import LeaseServer
from maglev_haptics.hardware.link.link_checks import (
    InboundGate, LinkLimits, check_command, check_lease_request, log_to_stderr)


@dataclass
class CoilOutputContract:
    """What the card may be asked for: ``n_coils`` currents within ``current_limit_a``
    (A), at ``amps_per_volt`` (A/V) of amplifier transconductance, by an application
    that flies ``instrument`` (the one levitated over these coils)."""

    n_coils: int
    current_limit_a: float
    amps_per_volt: float
    instrument: str

    def __post_init__(self):
        if not (np.isfinite(self.amps_per_volt) and self.amps_per_volt > 0):
            raise ValueError(f"amps_per_volt = {self.amps_per_volt}: must be a finite "
                             "number > 0 (A/V)")

    def limits(self) -> LinkLimits:
        return LinkLimits(n_coils=self.n_coils, n_markers=0,
                          current_limit_a=self.current_limit_a)


def coil_voltages(message: coil_currents_t, contract: CoilOutputContract) -> np.ndarray:
    """Volts (n_coils,) for a command within the contract (zeros with the power cut);
    raises Refused (``hardware/link/link_checks.py``) for one outside it."""
    check_command(message, contract.limits())
    if not message.power_enabled:
        return np.zeros(contract.n_coils)
    return np.asarray(message.current_a, dtype=float) / contract.amps_per_volt


class CommandLink:
    """The device's end of the link without the card: lease requests and commands
    in (raw LCM data), the lease's answers out (``publish_reply``), and the
    commands that pass every check handed to ``apply(message)``. Times are
    ``clock()``'s (s, monotonic)."""

    def __init__(self, contract: CoilOutputContract, *, apply: Callable,
                 publish_reply: Callable, lease_timeout_s: float,
                 command_channel: str = "COIL_CURRENTS_COMMANDED",
                 lease_channel: str = "LEASE_REQUEST", clock: Callable = time.monotonic,
                 log: Callable[[str], None] = log_to_stderr):
        self._apply = apply
        self._clock = clock
        self.lease = LeaseServer(timeout_s=lease_timeout_s, publish_reply=publish_reply,
                                 instrument=contract.instrument)
        limits = contract.limits()
        self.commands = InboundGate(command_channel, coil_currents_t,
                                    lambda message: check_command(message, limits),
                                    session_of=lambda message: message.session,
                                    admit=self.lease.admit, log=log)
        self.requests = InboundGate(lease_channel, lease_t, check_lease_request,
                                    session_of=lambda message: message.session,
                                    admit=self.lease.admit_request, log=log)
        self.applied = 0

    def on_request(self, data: bytes) -> None:
        now_s = self._clock()
        message = self.requests.accept(data, now_s)
        if message is not None:
            self.lease.request(message, now_s)

    def on_command(self, data: bytes) -> bool:
        """Whether the command was applied."""
        now_s = self._clock()
        message = self.commands.accept(data, now_s)
        if message is None:
            return False
        self.lease.keep_alive(now_s)
        self._apply(message)
        self.applied += 1
        return True

    def on_tick(self) -> None:
        self.lease.on_tick(self._clock())

    def counts(self) -> dict:
        return {"applied": self.applied, **self.commands.counts(),
                "lease": {"requests_refused": self.requests.counts()["refused"],
                          **self.lease.counts()}}


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

    def apply(self, message: coil_currents_t) -> None:
        """Write one command; raises Refused, writing nothing, for one outside the
        contract (only the lease and the sequence are left to ``serve``)."""
        volts = coil_voltages(message, self._contract)
        self._task.write(volts.tolist(), auto_start=True)

    def serve(self, lcm, channel: str, duration_s: float, command_timeout_s: float, *,
              lease_channel: str, reply_lcm, reply_channel: str,
              lease_timeout_s: float) -> dict:
        """Apply every good command on ``channel`` of ``lcm`` for ``duration_s`` s (wall
        clock), the lease's requests on ``lease_channel`` answered on ``reply_channel``
        of ``reply_lcm``; the coils off whenever the newest good command is older than
        ``command_timeout_s`` (s: the application stopped, or its commands were
        refused) and at the end. Returns ``CommandLink.counts()`` and "timeouts"."""
        newest = [-float("inf")]  # when the newest good command was applied (monotonic s)

        def apply(message):
            self.apply(message)
            newest[0] = time.monotonic()

        link = CommandLink(self._contract, apply=apply, lease_timeout_s=lease_timeout_s,
                           publish_reply=lambda message: publish(reply_lcm, reply_channel,
                                                                 message),
                           command_channel=channel, lease_channel=lease_channel)
        lcm.subscribe(lease_channel, lambda _, data: link.on_request(data))
        lcm.subscribe(channel, lambda _, data: link.on_command(data))
        end = time.monotonic() + duration_s
        off = True
        timeouts = 0
        try:
            while time.monotonic() < end:
                lcm.handle_timeout(1)
                link.on_tick()
                stale = time.monotonic() - newest[0] > command_timeout_s
                if stale and not off:
                    self._task.write([0.0] * self._contract.n_coils, auto_start=True)
                    timeouts += 1
                off = stale
        finally:
            self.close()
        return {**link.counts(), "timeouts": timeouts}

    def close(self) -> None:
        self._task.write([0.0] * self._contract.n_coils, auto_start=True)  # coils off
        self._task.close()

