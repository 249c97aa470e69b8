"""Service processes of one ``openfusion run`` on this machine: start, watch, stop; and the
run's stop signals.

The launcher starts each service as ``python -m openfusion.app.cli service NAME`` connected to
the run's router session, with its output in ``OUT/logs/NAME.log``, and stops them with
SIGTERM (then SIGKILL after a grace period). Each service runs in its own session (process
group), so the Ctrl-C of a terminal reaches only the launcher, which decides what the services
do (:class:`StopSignals`); and each one ends with its launcher however the launcher ends, even
by SIGKILL (:func:`follow_launcher`: Linux sends it SIGTERM when the launcher dies).

A service that dies is reported by :class:`RunError` with the reason taken from its log
(:meth:`ServiceProcess.reason`: the last line of a traceback, the service's one-line error) and
the last lines of the log as ``details``.

Supervision (:class:`RestartPolicy`, ``openfusion run``'s ``--max-restarts`` and
``--restart-backoff-s``): a service that exits while nobody asked it to stop is started again
with the same command, after ``backoff_s``, doubled for each restart of that service (at most
``backoff_max_s``), up to ``max_restarts`` times; each restart is logged with the reason from the
dead process's log (a warning line, and a marker line in the service's own log, which the new
process appends to) and counted per service (:attr:`Cluster.restarts`). The restarted process gets
its restart count in :data:`~openfusion.services.common.RESTARTS_ENV`, which its health stats
publish as the ``restarts`` counter. A service that exits with code 2 (its config or arguments are
bad: a restart cannot help) or dies once more past the limit ends the run with :class:`RunError`,
as without supervision.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

from openfusion.errors import Interrupted, OpenFusionError
from openfusion.services.common import RESTARTS_ENV

logger = logging.getLogger(__name__)

#: Set in each service's environment: the launcher's pid (:func:`follow_launcher`).
LAUNCHER_PID_ENV = "OPENFUSION_LAUNCHER_PID"
#: Lines of a dead service's log shown above the error.
TAIL_LINES = 10


class RunError(OpenFusionError):
    """The run cannot continue: a service died or did not come up (the message says which).

    ``details``: lines the command shows above its one-line error (the end of the service's log)."""

    def __init__(self, message: str, *, details: str = "") -> None:
        super().__init__(message)
        self.details = details


def follow_launcher() -> None:
    """In a service started by the launcher (:data:`LAUNCHER_PID_ENV` set): ask Linux for SIGTERM
    when the launcher dies (``PR_SET_PDEATHSIG``), and exit at once when it is already gone. Does
    nothing elsewhere."""
    text = os.environ.get(LAUNCHER_PID_ENV, "")
    if not text.isdigit() or not sys.platform.startswith("linux"):
        return
    import ctypes

    pr_set_pdeathsig = 1
    try:
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError) as exc:  # not fatal: the launcher still stops its services itself
        logger.debug("prctl(PR_SET_PDEATHSIG) unavailable: %s", exc)
        return
    if os.getppid() != int(text):
        raise SystemExit(f"the launcher (pid {text}) is gone; not starting")


def _reason_and_tail(text: str, lines: int = TAIL_LINES) -> tuple[str, list[str]]:
    """(why a process ended, the last ``lines`` non-empty lines of its log up to that line).

    The reason is the exception line of the last traceback, else the command's one-line error
    (``openfusion ...: error: ...``), else the last ERROR/CRITICAL log line; else there is none
    (``""``) and the tail is the log's last lines."""
    rows = [line.rstrip() for line in text.splitlines() if line.strip()]
    if not rows:
        return "", []
    end = len(rows) - 1
    starts = [i for i, line in enumerate(rows) if line.startswith("Traceback (most recent call last)")]
    one_line = [i for i, line in enumerate(rows) if line.startswith("openfusion ") and ": error: " in line]
    logged = [i for i, line in enumerate(rows) if line.startswith(("ERROR", "CRITICAL"))]
    if starts:  # the first unindented line after the last "Traceback" is the exception
        end = next((i for i in range(starts[-1] + 1, len(rows)) if not rows[i][:1].isspace()), end)
    elif one_line:
        end = one_line[-1]
    elif logged:
        end = logged[-1]
    else:
        return "", rows[-lines:]
    return rows[end].strip(), rows[max(0, end - lines + 1): end + 1]


#: Exit code of a service refusing its config or arguments (UserError): restarting cannot help.
USAGE_EXIT_CODE = 2


@dataclass(frozen=True)
class RestartPolicy:
    """How :class:`Cluster` restarts a service that exits unexpectedly (module docstring)."""

    max_restarts: int = 3
    backoff_s: float = 1.0
    backoff_max_s: float = 30.0

    def delay_s(self, restarts_so_far: int) -> float:
        """Seconds to wait before restart number ``restarts_so_far + 1`` (exponential backoff)."""
        return min(self.backoff_max_s, self.backoff_s * (2.0 ** restarts_so_far))


@dataclass
class ServiceProcess:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    #: Stopped on purpose (``Cluster.stop(name)``): not a death :meth:`Cluster.check_alive` reports.
    stopped: bool = False
    #: The run goes on without it (an encoder worker: the pool sends its frames elsewhere): past the
    #: restart limit, or with no restart policy, its death is logged, not raised.
    optional: bool = False
    #: The ``openfusion service`` it runs when that is not its name (encoder workers ``encoder-w1``...).
    service: str | None = None
    #: The command-line arguments and extra environment it was started with (a restart reuses them).
    extra: tuple[str, ...] = ()
    env: dict[str, str] | None = None
    #: Where this process's output begins in its log (a restarted one appends to the same file).
    log_offset: int = 0
    #: How many times the service was restarted before this process; when the next restart is due.
    restarts: int = 0
    restart_due: float | None = None

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_text(self) -> str:
        """This process's part of its log (not what an earlier process of the service wrote)."""
        try:
            with open(self.log_path, "rb") as f:
                f.seek(self.log_offset)
                return f.read().decode(errors="replace")
        except OSError:
            return ""

    def tail(self, lines: int = 15) -> str:
        return "\n".join(self.log_text().splitlines()[-lines:])

    def reason(self) -> tuple[str, list[str]]:
        """Why the process ended and the log lines leading to it (:func:`_reason_and_tail`)."""
        return _reason_and_tail(self.log_text())

    def how_it_ended(self) -> tuple[str, str, str, list[str]]:
        """(``"was killed by SIGKILL"`` / ``"exited with code 1"``, the reason for a message, the
        reason line as the log says it, the log lines leading to it)."""
        reason, tail = self.reason()
        said = reason
        code = self.proc.returncode
        if code is not None and code < 0:
            try:
                how = f"was killed by {signal.Signals(-code).name}"
            except ValueError:
                how = f"was killed by signal {-code}"
        else:
            how = f"exited with code {code}"
            said = reason = reason or (tail[-1].strip() if tail else "")  # no error line: its last words
        if reason.startswith("openfusion ") and ": error: " in reason:  # the service's own one-line error
            reason = reason.split(": error: ", 1)[1]
        return how, reason, said, tail

    def death(self, *, after: str = "") -> RunError:
        """The :class:`RunError` of this dead process: the reason in the one-line message, the
        last lines of its log as details; ``after``: words after the reason (``restarted 3 times``)."""
        how, reason, said, tail = self.how_it_ended()
        message = (f"the {self.name} service {how}" + (f": {reason}" if reason else "")
                   + (f" ({after})" if after else "") + f" (log: {self.log_path})")
        # The log's last lines above the error, when they say more than the reason.
        details = ("\n".join([f"last lines of {self.log_path}:", *(f"  {line}" for line in tail)])
                   if tail and [line.strip() for line in tail] != [said] else "")
        return RunError(message, details=details)


class StopSignals:
    """SIGINT and SIGTERM during a run (a context manager; main thread only, else it does nothing).

    The first signal does not interrupt anything: it sets :attr:`requested` (the signal's name),
    which the run checks between steps to stop playback and keep its work. A second signal aborts:
    ``on_abort`` runs at once (the launcher kills its services) and KeyboardInterrupt is raised in
    the main thread, its message ``aborted by a second SIGINT: <aborted>``. The previous handlers
    come back on exit.
    """

    def __init__(self, on_abort: Callable[[], None] | None = None, *, aborted: str = "no map was saved") -> None:
        self.on_abort = on_abort
        self.aborted = aborted
        self.requested: str | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        if self.requested is None:
            self.requested = signal.Signals(signum).name
            return
        if self.on_abort is not None:
            self.on_abort()
        raise KeyboardInterrupt(f"aborted by a second {signal.Signals(signum).name}: {self.aborted}")

    def interrupted(self, what: str) -> Interrupted:
        """The :class:`Interrupted` error that ends a run stopped by the first signal."""
        return Interrupted(f"interrupted: {what}")


@dataclass
class Cluster:
    """Service processes of one embedded run, connected to a router session of this process."""

    map_id: str
    endpoint: str
    log_dir: Path
    #: The run's config file (``RunConfig``); when set, children get it and no OPENFUSION_* variables
    #: (the file already holds them, and the environment must not override the launcher's options).
    config_file: Path | None = None
    processes: dict[str, ServiceProcess] = field(default_factory=dict)
    #: None: a service that dies ends the run (:meth:`check_alive` raises); else it is restarted.
    restart_policy: RestartPolicy | None = None

    def base_args(self) -> list[str]:
        args = ["--map", self.map_id, "--mode", "peer", "--connect", self.endpoint, "--no-multicast",
                "--listen", "tcp/127.0.0.1:0"]
        return args + (["--config", str(self.config_file)] if self.config_file is not None else [])

    def _environment(self, extra: dict[str, str] | None) -> dict[str, str]:
        env = dict(os.environ)
        if self.config_file is not None:
            env = {k: v for k, v in env.items() if not k.startswith("OPENFUSION_") or k == "OPENFUSION_DEBUG"}
        return {**env, LAUNCHER_PID_ENV: str(os.getpid()), **(extra or {})}

    def start(self, name: str, extra: Sequence[str] = (), env: dict[str, str] | None = None, *,
              restarts: int = 0, service: str | None = None, optional: bool = False) -> ServiceProcess:
        """Start ``openfusion service SERVICE`` (default: ``name``) as process ``name`` (its log is
        ``name.log``; several encoder workers are one service under several names); ``optional``:
        the run goes on without it (:attr:`ServiceProcess.optional`)."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{name}.log"
        log = open(log_path, "ab")  # noqa: SIM115 - closed when the process ends (child keeps its fd)
        offset = log.tell()
        cmd = [sys.executable, "-m", "openfusion.app.cli", "service", service or name, *self.base_args(), *extra]
        environment = self._environment(env)
        environment[RESTARTS_ENV] = str(restarts)
        # Its own session: a terminal's Ctrl-C goes to the launcher only (StopSignals decides).
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=environment, start_new_session=True)
        log.close()
        sp = ServiceProcess(name, proc, log_path, optional=optional, service=service, extra=tuple(extra), env=env,
                            log_offset=offset, restarts=restarts)
        self.processes[name] = sp
        return sp

    @property
    def restarts(self) -> dict[str, int]:
        """Restarts of each service so far (0 for one never restarted)."""
        return {name: sp.restarts for name, sp in self.processes.items()}

    @property
    def restarting(self) -> bool:
        """A service is dead and its restart is pending."""
        return any(sp.restart_due is not None and not sp.stopped for sp in self.processes.values())

    def check_alive(self) -> None:
        """Without a restart policy: RunError (with the reason from its log) for a service that
        died; one stopped on purpose is not reported. With one: :meth:`supervise`."""
        if self.restart_policy is not None:
            self.supervise()
            return
        for sp in self.processes.values():
            if not sp.stopped and not sp.alive():
                if sp.optional:
                    sp.stopped = True
                    logger.warning("%s; the run goes on without it", sp.death())
                    continue
                raise sp.death()

    def supervise(self, now: float | None = None) -> list[str]:
        """Restart the services that died unexpectedly once their backoff has passed (module
        docstring); the names restarted now. RunError for one that cannot be restarted."""
        policy = self.restart_policy or RestartPolicy(max_restarts=0)
        now = time.monotonic() if now is None else now
        restarted: list[str] = []
        for name, sp in list(self.processes.items()):
            if sp.stopped or sp.alive():
                continue
            if sp.restart_due is None:  # just found dead: decide
                if sp.proc.returncode == USAGE_EXIT_CODE:
                    raise sp.death(after="its config or arguments are refused; not restarted")
                if sp.restarts >= policy.max_restarts:
                    death = sp.death(after=f"restarted {sp.restarts} times, the limit" if sp.restarts else "")
                    if sp.optional:
                        sp.stopped = True
                        logger.warning("%s; the run goes on without it", death)
                        continue
                    raise death
                how, reason, _said, _tail = sp.how_it_ended()
                delay = policy.delay_s(sp.restarts)
                sp.restart_due = now + delay
                logger.warning("the %s service %s%s; restarting it in %.1f s (restart %d of at most %d)",
                               name, how, f": {reason}" if reason else "", delay, sp.restarts + 1,
                               policy.max_restarts)
                self._mark_log(sp, f"{how}{': ' + reason if reason else ''}; restart {sp.restarts + 1} "
                               f"in {delay:.1f} s")
            if now >= sp.restart_due:
                self.start(name, sp.extra, sp.env, restarts=sp.restarts + 1, service=sp.service, optional=sp.optional)
                restarted.append(name)
        return restarted

    @staticmethod
    def _mark_log(sp: ServiceProcess, text: str) -> None:
        try:
            with open(sp.log_path, "a") as log:
                log.write(f"---- openfusion run: the {sp.name} service {text} ----\n")
        except OSError as exc:  # the warning on the launcher's stderr says it anyway
            logger.debug("cannot mark %s: %s", sp.log_path, exc)

    def kill(self) -> None:
        """SIGKILL every service still running, without waiting (safe in a signal handler)."""
        for sp in self.processes.values():
            sp.stopped = True
            try:
                sp.proc.kill()
            except OSError as exc:  # already gone
                logger.debug("kill %s: %s", sp.name, exc)

    def stop(self, name: str | None = None, *, timeout_s: float = 15.0) -> None:
        """SIGTERM the service ``name`` (default: all), wait up to ``timeout_s``, then SIGKILL. A
        stop that is itself interrupted (an exception, a second Ctrl-C) still kills them."""
        targets = [self.processes[name]] if name else list(self.processes.values())
        try:
            for sp in targets:
                sp.stopped = True
                if sp.alive():
                    sp.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + timeout_s
            for sp in targets:
                try:
                    sp.proc.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    logger.warning("%s did not stop within %.0f s; killing it", sp.name, timeout_s)
                    sp.proc.kill()
                    sp.proc.wait(5)
        finally:
            for sp in targets:
                if sp.alive():
                    sp.proc.kill()


def wait_for_services(client: Any, cluster: Cluster, names: set[str], timeout_s: float,
                      should_stop: Callable[[], bool] = lambda: False) -> None:
    """Wait until every service in ``names`` is alive (RunError when one dies or the time is up);
    returns early when ``should_stop()``."""
    deadline = time.monotonic() + timeout_s
    while not should_stop():
        cluster.check_alive()
        live = set(client.live_services(timeout_s=1.0))
        if names <= live:
            return
        if time.monotonic() > deadline:
            raise RunError(f"services {sorted(names - live)} did not come up within {timeout_s:.0f} s "
                           f"(logs in {cluster.log_dir})")
        time.sleep(0.3)


