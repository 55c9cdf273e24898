"""``--assist-light`` specifications: parse (pure), then open only what the user named.

Forms:

* ``serial:PORT:rts`` / ``serial:PORT:dtr``: a light keyed from the RTS or DTR line of
  the serial port (or pyserial URL) ``PORT`` (:class:`~tdfd.light.serial_line.SerialLineLight`).
  ``PORT`` may itself hold colons (``loop://``, ``socket://host:1234``, ``COM3``); the
  line is the text after the last colon.
* ``cmd:ON_CMD,OFF_CMD``: two commands (:class:`~tdfd.light.command.CommandLight`),
  split at the first comma that is not inside quotes; each is split with
  :func:`shlex.split` and run without a shell. A comma inside a command must be quoted.

Anything else is a :class:`~tdfd.errors.LightSpecError` naming the accepted forms.

Example:
    >>> parse_light_spec("serial:/dev/ttyUSB0:rts")
    LightSpec(kind='serial', port='/dev/ttyUSB0', line='rts', on_cmd=None, off_cmd=None)
    >>> parse_light_spec("cmd:relay on,relay off").off_cmd
    'relay off'
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import LightSpecError
from .base import AssistLight
from .command import DEFAULT_COMMAND_TIMEOUT_S, CommandLight
from .serial_line import LINES, SerialLineLight, open_serial_line

__all__ = ["LightSpec", "parse_light_spec", "open_light", "SPEC_FORMS"]

#: the accepted forms, as the error message lists them.
SPEC_FORMS = "serial:PORT:rts, serial:PORT:dtr or cmd:ON_CMD,OFF_CMD"


@dataclass(frozen=True)
class LightSpec:
    """A parsed ``--assist-light`` value (nothing opened).

    Attributes:
        kind: ``"serial"`` or ``"cmd"``.
        port: the serial port or URL (``serial``).
        line: ``"rts"`` or ``"dtr"`` (``serial``).
        on_cmd, off_cmd: the commands (``cmd``).
    """

    kind: str
    port: str | None = None
    line: str | None = None
    on_cmd: str | None = None
    off_cmd: str | None = None

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.port}:{self.line}"
        return f"cmd:{self.on_cmd},{self.off_cmd}"


def _split_commands(text: str) -> tuple[str, str] | None:
    quote = None
    escaped = False
    for i, ch in enumerate(text):
        if escaped:
            escaped = False
        elif ch == "\\" and quote != "'":
            escaped = True
        elif quote is not None:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == ",":
            return text[:i].strip(), text[i + 1 :].strip()
    return None


def parse_light_spec(text: str) -> LightSpec:
    """Parse an ``--assist-light`` value (opens nothing).

    Raises:
        LightSpecError: not one of :data:`SPEC_FORMS`.
    """
    raw = str(text).strip()
    kind, sep, rest = raw.partition(":")
    kind = kind.lower()
    if sep and kind == "serial":
        port, sep2, line = rest.rpartition(":")
        if sep2 and port and line.lower() in LINES:
            return LightSpec("serial", port=port, line=line.lower())
        raise LightSpecError(f"--assist-light {raw!r}: a serial light is serial:PORT:rts or serial:PORT:dtr "
                             f"(the line after the last colon, got {line!r})")
    if sep and kind == "cmd":
        parts = _split_commands(rest)
        if parts is not None and parts[0] and parts[1]:
            return LightSpec("cmd", on_cmd=parts[0], off_cmd=parts[1])
        raise LightSpecError(f"--assist-light {raw!r}: a command light is cmd:ON_CMD,OFF_CMD (two commands, one comma "
                             "between them; quote a comma inside a command)")
    raise LightSpecError(f"--assist-light {raw!r}: unknown form; use {SPEC_FORMS}")


def open_light(spec: LightSpec | str, command_timeout_s: float = DEFAULT_COMMAND_TIMEOUT_S) -> AssistLight:
    """Open the light the user named (off on return).

    Raises:
        LightSpecError: an unparsable spec.
        LightConnectionError: the serial port does not exist or cannot be opened.
        ModemLineError: the port refuses modem-line control (a pty, the wrong port).
        LightVerifyError: the line does not read back off.
        LightCommandError: the off command (run once to start from a known state) failed.
        InputError: an empty or unsplittable command.
    """
    if isinstance(spec, str):
        spec = parse_light_spec(spec)
    if spec.kind == "serial":
        assert spec.port is not None and spec.line is not None
        port = open_serial_line(spec.port, spec.line)
        try:
            return SerialLineLight(port, spec.line, owns_port=True)
        except BaseException:
            port.close()
            raise
    assert spec.on_cmd is not None and spec.off_cmd is not None
    light = CommandLight(spec.on_cmd, spec.off_cmd, timeout_s=command_timeout_s)
    light.off()  # a known state, and a bad off command is reported before anything moves
    return light
