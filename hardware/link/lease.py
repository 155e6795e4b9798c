"""One controller at a time: the device's lease, both ends.

An application draws a random session id when it starts (``new_session``) and
puts it in every command (``coil_currents_t.session``). It asks for the lease on
``LEASE_REQUEST`` (a ``lease_t`` REQUEST with its session, host and process id);
the device grants it if nobody holds it (or the holder's lease has lapsed) and
answers on ``LEASE`` who holds it, at once and every ``REPLY_PERIOD_S``. The
holder keeps it by commanding: once its commands have been silent for
``timeout_s`` it lapses. An application lets it go (RELEASE) when it stops.

Both ends name their instrument: the device refuses a request for another one
(``wrong_instrument``), and an application that reads the device's answer naming
another stops with ``InstrumentMismatchError``: its wrench model, and so every
current it would command, would be another device's.

The device refuses every command whose session is not the holder's (counted as
``other_session``), so a second application's commands never reach the coils; it
reads the device's answer naming another holder and stops with
``DeviceInUseError``. LCM has no authentication: the lease keeps well-meaning
programs apart, not an attacker on the same network (ttl=0 keeps the traffic on
this host; a lab that must cross hosts uses a private network).
"""

from __future__ import annotations

import atexit
import math
import os
import secrets
import socket
import weakref
from typing import Callable, Optional

from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.link.lcm_messages import lease_t
from maglev_haptics.hardware.link.link_checks import Refused

REPLY_PERIOD_S = 0.1  # the device says who holds the lease this often (s)
REQUEST_PERIOD_S = 0.05  # an application not yet granted asks again this often (s)
US_PER_S = 1_000_000


class DeviceInUseError(RuntimeError):
    """Another application holds the device's lease: this one commands nothing."""


class InstrumentMismatchError(ValueError):
    """The device carries another instrument than the application's scenario flies."""


def new_session() -> int:
    """A random, non-zero 62-bit session id."""
    return secrets.randbits(62) | 1


def describe_holder(message) -> str:
    """"session 0x.., process PID on HOST" as far as a lease_t says."""
    where = []
    if message.pid:
        where.append(f"process {message.pid}")
    if message.host:
        where.append(f"on {message.host}")
    return f"session {message.session:#x}" + (f", {' '.join(where)}" if where else "")


class LeaseServer:
    """The device's end: who holds the lease. ``publish_reply(message)`` sends an
    answer (on ``LEASE``); times are the device's clock (s); ``instrument`` is the one
    on the device (``DeviceConfig.instrument``)."""

    def __init__(self, *, timeout_s: float, publish_reply: Callable[[lease_t], None],
                 instrument: str):
        self.timeout_s = float(timeout_s)
        self.instrument = instrument
        self._publish_reply = publish_reply
        self.holder = lease_t()  # session 0: nobody
        self.holder.action = lease_t.FREE
        self._last_s = -math.inf  # when the holder last asked or commanded
        self._replied_s = -math.inf
        self._sequence = 0
        self.grants = 0

    def _lapse(self, now_s: float) -> None:
        if self.holder.session and now_s - self._last_s > self.timeout_s:
            self._free()

    def _free(self) -> None:
        self.holder = lease_t()
        self.holder.action = lease_t.FREE

    def admit_request(self, message: lease_t, now_s: float) -> None:
        """An application's REQUEST or RELEASE (checked by ``check_lease_request``):
        where another session holds the lease, answers who does and raises
        Refused("other_session"); a REQUEST for another instrument raises
        Refused("wrong_instrument")."""
        self._lapse(now_s)
        if message.action == lease_t.REQUEST and message.instrument != self.instrument:
            self.reply(now_s)
            raise Refused("wrong_instrument", f"instrument = {message.instrument!r} "
                          f"({describe_holder(message)}): the device carries "
                          f"{self.instrument!r}")
        if self.holder.session not in (0, message.session):
            self.reply(now_s)
            action = "REQUEST" if message.action == lease_t.REQUEST else "RELEASE"
            raise Refused("other_session", f"session = {message.session:#x} "
                          f"({describe_holder(message)}) sent {action}: the lease is held "
                          f"by {describe_holder(self.holder)}")

    def request(self, message: lease_t, now_s: float) -> None:
        """An admitted REQUEST (granted) or RELEASE (freed); the answer goes out."""
        if message.action == lease_t.RELEASE:
            self._free()
        else:
            if self.holder.session != message.session:
                self.grants += 1
            self.holder = lease_t()
            self.holder.action = lease_t.HELD
            self.holder.session, self.holder.pid = message.session, message.pid
            self.holder.host = message.host
            self._last_s = now_s
        self.reply(now_s)

    def admit(self, command, now_s: float) -> None:
        """Raises Refused("other_session") unless ``command`` is the holder's."""
        self._lapse(now_s)
        if command.session == 0 or command.session != self.holder.session:
            holder = (f"held by {describe_holder(self.holder)}" if self.holder.session
                      else "nobody holds it (ask on LEASE_REQUEST first)")
            raise Refused("other_session", f"session = {command.session:#x}: not the "
                          f"lease's; {holder}")

    def keep_alive(self, now_s: float) -> None:
        """The holder's command was accepted: its lease runs on."""
        self._last_s = now_s

    def reply(self, now_s: float) -> None:
        """Say who holds the lease now."""
        self._lapse(now_s)
        self._sequence += 1
        message = lease_t()
        message.sequence = self._sequence
        message.utime = int(round(now_s * US_PER_S))
        message.action = self.holder.action
        message.session, message.pid, message.host = (
            self.holder.session, self.holder.pid, self.holder.host)
        message.instrument = self.instrument
        self._replied_s = now_s
        self._publish_reply(message)

    def on_tick(self, now_s: float) -> None:
        """Every tick: answer again every REPLY_PERIOD_S."""
        if now_s - self._replied_s >= REPLY_PERIOD_S:
            self.reply(now_s)

    def counts(self) -> dict:
        return {"holder": describe_holder(self.holder) if self.holder.session else None,
                "grants": self.grants}


class LeaseClient:
    """The application's end: its session, asked for until granted.

    ``lcm``/``channel``: where requests go (the command URL's ``LEASE_REQUEST``).
    ``on_reply`` reads the device's answers: one naming another holder before this
    session was granted raises ``DeviceInUseError``; ``on_tick`` asks again every
    ``REQUEST_PERIOD_S`` until granted, and raises TimeoutError if no grant came
    within ``wait_s``; an answer from a device that carries another instrument than
    ``instrument`` raises ``InstrumentMismatchError``. ``release()`` (also at exit)
    lets the lease go."""

    def __init__(self, *, lcm, channel: str, wait_s: float, instrument: str,
                 session: Optional[int] = None):
        self.session = new_session() if session is None else int(session)
        self.instrument = instrument
        self.host = socket.gethostname()
        self.pid = os.getpid()
        self._lcm = lcm
        self._channel = channel
        self._wait_s = float(wait_s)
        self._sequence = 0
        self._first_request_s = None
        self._requested_s = -math.inf
        self.granted = False
        self.granted_at_s: Optional[float] = None
        self.lapses = 0  # times the device's answer said it no longer held for us
        self.lost_to: Optional[str] = None
        self._released = False
        # The device answered this session's last request that another holds the lease
        # or that it carries another instrument: a RELEASE would be refused.
        self._refused = False
        reference = weakref.ref(self)
        atexit.register(lambda: reference() is not None and reference().release())

    def _send(self, action: int, now_s: float) -> None:
        self._sequence += 1
        message = lease_t()
        message.sequence = self._sequence
        message.utime = int(round(now_s * US_PER_S))
        message.session, message.action = self.session, action
        message.pid, message.host = self.pid, self.host
        message.instrument = self.instrument
        publish(self._lcm, self._channel, message)

    def on_tick(self, now_s: float) -> None:
        if self.granted or self._released:
            return
        if self._first_request_s is None:
            self._first_request_s = now_s
        elif self.granted_at_s is None and now_s - self._first_request_s > self._wait_s:
            raise TimeoutError(
                f"the station granted no lease within {self._wait_s:g} s of asking on "
                f"{self._channel!r}: is it a device-sim or driver of this version, which "
                "answers the lease's requests?")
        if now_s - self._requested_s >= REQUEST_PERIOD_S:
            self._requested_s = now_s
            self._refused = False
            self._send(lease_t.REQUEST, now_s)

    def on_reply(self, message: lease_t, now_s: float) -> None:
        if message.instrument != self.instrument:  # also a device restarted mid-run
            never_held = self.granted_at_s is None
            self._refused = never_held  # the device refuses it: nothing to release
            commanded = ("this one commanded no coil" if never_held
                         else "this one stops commanding")
            raise InstrumentMismatchError(
                f"the device carries the {message.instrument!r} instrument; this scenario "
                f"flies {self.instrument!r} (device.instrument): run the device and the "
                f"application with the same device; {commanded}")
        if message.action == lease_t.HELD and message.session == self.session:
            if not self.granted:
                self.granted, self.granted_at_s = True, now_s
            return
        if message.action == lease_t.HELD and not self.granted and self.granted_at_s is None:
            self._refused = True  # another holds it: nothing to release
            raise DeviceInUseError(
                f"the device is in use by another application ({describe_holder(message)}); "
                "this one commanded no coil")
        if self.granted:  # held by another, or free: the lease lapsed
            self.granted = False
            self.lapses += 1
            self._first_request_s = None
            if message.action == lease_t.HELD:
                self.lost_to = describe_holder(message)

    def release(self) -> None:
        """Let the lease go (once; not after the device answered that another holds it
        or that it carries another instrument: this session holds nothing)."""
        if self._released:
            return
        self._released = True
        if self._refused:
            return
        try:
            self._send(lease_t.RELEASE, 0.0)
        except (OSError, RuntimeError):  # the LCM socket is already gone at exit
            pass

    def counts(self) -> dict:
        return {"session": f"{self.session:#x}", "granted_at_s": self.granted_at_s,
                "lapses": self.lapses, "lost_to": self.lost_to}
