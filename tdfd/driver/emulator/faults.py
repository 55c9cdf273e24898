"""Seeded fault injection for the emulated Lens Driver 4 (:class:`Faults`)."""

from __future__ import annotations

import logging
import random
from dataclasses import dataclass, field, fields

from ...errors import InputError
from .. import protocol as p

__all__ = ["Faults", "KINDS"]

#: the probabilistic fault kinds (fields of :class:`Faults`).
KINDS = ("bad_crc", "drop", "late", "garbage", "corrupt")

log = logging.getLogger(__name__)


@dataclass
class Faults:
    """Seeded fault injection on the emulator's replies, on the commands it receives, and on the port.

    Probabilities are per reply (``corrupt``: per command write) and independent; a
    probability of 1 always fires. Set
    ``limit`` to stop after that many injected faults (e.g. ``Faults(drop=1, limit=1)``
    drops exactly the next reply). Replace or mutate the server's faults at run time.

    Attributes:
        bad_crc: probability of corrupting a reply's CRC (a ``Ready`` reply: its text).
        drop: probability of not sending a reply.
        late: probability of delaying a reply (and those queued after it) by ``late_s``.
        garbage: probability of sending 1…``garbage_max_bytes`` random bytes before a reply.
        corrupt: probability of corrupting one byte of a command on its way to the device
            (the device answers ``E 1`` for a bad CRC, ``E 3`` for a mangled prefix, and a
            set command that has no reply of its own is not carried out).
        late_s: delay of a late reply, seconds.
        garbage_max_bytes: most garbage bytes at once.
        disconnect_after: close the pty after this many further commands (0: at the
            next opportunity); ``None``: never.
        limit: most faults to inject (disconnect excluded); ``None``: no limit.
        seed: seed of :attr:`rng`.
        rng: the random generator (``random.Random(seed)``).
        injected: faults injected so far.
    """

    bad_crc: float = 0.0
    drop: float = 0.0
    late: float = 0.0
    garbage: float = 0.0
    corrupt: float = 0.0
    late_s: float = 0.3
    garbage_max_bytes: int = 8
    disconnect_after: int | None = None
    limit: int | None = None
    seed: int = 0
    rng: random.Random = field(init=False, repr=False, compare=False)
    injected: int = field(default=0, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in KINDS:
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InputError(f"fault probability {name} must be in [0, 1], got {value}")
        if self.late_s < 0 or self.garbage_max_bytes < 1:
            raise InputError("late_s must be >= 0 and garbage_max_bytes >= 1")
        self.rng = random.Random(self.seed)

    @classmethod
    def parse(cls, specs: list[str] | tuple[str, ...], seed: int = 0) -> Faults:
        """Build from ``NAME=VALUE`` strings (the CLI's ``--fault``).

        Examples:
            >>> Faults.parse(["drop=0.5", "late_s=0.1", "disconnect_after=3"])
            Faults(bad_crc=0.0, drop=0.5, late=0.0, garbage=0.0, corrupt=0.0, late_s=0.1, garbage_max_bytes=8, disconnect_after=3, limit=None, seed=0)
        """
        kinds = {f.name: f.type for f in fields(cls) if f.init}
        values: dict[str, object] = {"seed": seed}
        for spec in specs:
            name, sep, value = spec.partition("=")
            name = name.strip().replace("-", "_")
            if not sep or name not in kinds:
                raise InputError(f"bad fault {spec!r}: use NAME=VALUE with NAME one of {', '.join(kinds)}")
            kind = str(kinds[name])
            if value.strip().lower() in ("none", ""):
                values[name] = None
            else:
                try:
                    values[name] = int(value) if "int" in kind else float(value)
                except ValueError:
                    raise InputError(f"bad fault {spec!r}: {value!r} is not a number") from None
        return cls(**values)  # type: ignore[arg-type]

    def _roll(self, probability: float) -> bool:
        if probability <= 0.0 or (self.limit is not None and self.injected >= self.limit):
            return False
        hit = probability >= 1.0 or self.rng.random() < probability
        if hit:
            self.injected += 1
        return hit

    def apply(self, reply: bytes) -> tuple[bytes | None, float]:
        """Decide the fate of one reply.

        Returns:
            (bytes to send or ``None`` if dropped, delay in seconds).
        """
        if self._roll(self.drop):
            log.info("fault: dropping reply %s", reply.hex(" "))
            return None, 0.0
        out = bytes(reply)
        if self._roll(self.bad_crc):
            corrupted = bytearray(out)
            index = len(out) - 4 if out not in (p.HANDSHAKE_REPLY, p.BARE_ERROR_REPLY) else 0
            corrupted[max(index, 0)] ^= 0x5A
            out = bytes(corrupted)
            log.info("fault: bad CRC %s", out.hex(" "))
        delay = 0.0
        if self._roll(self.late):
            delay = self.late_s
            log.info("fault: reply late by %.3f s", delay)
        if self._roll(self.garbage):
            n = self.rng.randint(1, self.garbage_max_bytes)
            junk = bytes(self.rng.randrange(256) for _ in range(n))
            out = junk + out
            log.info("fault: %d garbage byte(s) before the reply", n)
        return out, delay

    def corrupt_command(self, data: bytes) -> bytes:
        """Decide the fate of bytes written to the device: maybe one byte XOR-ed with a random non-zero value."""
        if not data or not self._roll(self.corrupt):
            return bytes(data)
        bad = bytearray(data)
        index = self.rng.randrange(len(bad))
        bad[index] ^= self.rng.randint(1, 255)
        log.info("fault: command %s corrupted to %s", bytes(data).hex(" "), bytes(bad).hex(" "))
        return bytes(bad)
