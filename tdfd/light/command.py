"""A light switched by the user's own commands (``--assist-light cmd:ON_CMD,OFF_CMD``).

Each command is split with :func:`shlex.split` and run as a subprocess **without a
shell** (no globbing, pipes or variables: wrap them in a script if they are needed),
with a timeout. A command that cannot be started, times out (it is killed) or exits
non-zero raises :class:`~tdfd.errors.LightCommandError` with its exit status and the tail
of its stderr. After a failed ``on`` the ``off`` command is still run (the light may be
half on); a failed ``off`` leaves :attr:`~tdfd.light.base.AssistLight.is_on` ``True``.

Example:
    >>> import sys
    >>> light = CommandLight([sys.executable, "-c", "pass"], [sys.executable, "-c", "pass"])
    >>> light.on(); light.is_on
    True
    >>> light.off(); light.is_on
    False
"""

from __future__ import annotations

import logging
import shlex
import subprocess
from typing import Sequence

from ..errors import InputError, LightCommandError
from .base import AssistLight

__all__ = ["CommandLight", "DEFAULT_COMMAND_TIMEOUT_S"]

log = logging.getLogger(__name__)

#: default timeout of one light command (s).
DEFAULT_COMMAND_TIMEOUT_S = 5.0


def _argv(cmd: str | Sequence[str], what: str) -> list[str]:
    if isinstance(cmd, str):
        try:
            argv = shlex.split(cmd)
        except ValueError as exc:
            raise InputError(f"cannot split the light's {what} command {cmd!r}: {exc}") from exc
    else:
        argv = [str(a) for a in cmd]
    if not argv:
        raise InputError(f"the light's {what} command is empty")
    return argv


class CommandLight(AssistLight):
    """An on/off light switched by two commands.

    Args:
        on_cmd: the command that switches the light on (a string, split with
            :func:`shlex.split`, or an argv list).
        off_cmd: the command that switches it off.
        timeout_s: longest a command may run before it is killed (s).

    Raises:
        InputError: an empty or unsplittable command, or a timeout <= 0.
    """

    def __init__(self, on_cmd: str | Sequence[str], off_cmd: str | Sequence[str],
                 timeout_s: float = DEFAULT_COMMAND_TIMEOUT_S) -> None:
        super().__init__()
        self.on_argv, self.off_argv = _argv(on_cmd, "on"), _argv(off_cmd, "off")
        if not timeout_s > 0:
            raise InputError(f"the light command timeout must be > 0 s, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        self.name = f"cmd:{shlex.join(self.on_argv)},{shlex.join(self.off_argv)}"

    def _run(self, argv: list[str], what: str) -> None:
        text = shlex.join(argv)
        try:
            done = subprocess.run(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  timeout=self.timeout_s, check=False, shell=False)
        except subprocess.TimeoutExpired as exc:
            raise LightCommandError(f"light {what} command `{text}` did not finish within {self.timeout_s:g} s "
                                    "(killed)") from exc
        except OSError as exc:  # not found, not executable
            raise LightCommandError(f"cannot run the light {what} command `{text}`: {exc}") from exc
        if done.returncode != 0:
            tail = done.stderr.decode("utf-8", "replace").strip().splitlines()[-3:]
            raise LightCommandError(f"light {what} command `{text}` exited with status {done.returncode}"
                                    + (f": {' / '.join(tail)}" if tail else ""))
        log.debug("light %s command ran: %s", what, text)

    def _switch_on(self, pattern: str) -> None:
        self._run(self.on_argv, "on")

    def _switch_off(self) -> None:
        self._run(self.off_argv, "off")
