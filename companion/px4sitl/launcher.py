"""Start and stop one PX4 SITL instance with its built-in simulator (SIH).

    with PX4Sitl.from_config(cfg) as px4:      # fresh working folder, free instance, SIH vehicle applied
        px4.wait_preflight()                   # estimator settled: PX4 would arm now (30-40 s)
        ... fly against px4.offboard_url ...   # udpin://127.0.0.1:14540+N; ground truth on px4.truth_url

PX4 runs in its own session (a Ctrl-C in the terminal reaches the app, which hands the vehicle back, and
only then is PX4 stopped) and is stopped on every way out: ``stop()``/the context manager, ``atexit``, and
the kernel's parent-death signal when the process that started it dies, even by SIGKILL.

The instance is the first free one: its UDP ports are free on 127.0.0.1, PX4's own instance lock is free,
and we hold a lock file for it as long as PX4 runs, so parallel tests and runs never collide.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import hashlib
import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from companion.config import Config

ENV_VAR = "PX4_SITL_DIR"


@dataclass(frozen=True)
class PX4Status:
    armed: bool
    nav_mode: str  # PX4's name: Hold, Takeoff, Land, Offboard, Position, Descend, ...
    failsafe: bool


class PX4SitlError(RuntimeError):
    """PX4 SITL could not be found, started or made ready (the message is one line)."""


def instance_ports(n: int) -> dict[str, int]:
    """UDP ports of instance n (etc/init.d-posix/px4-rc.mavlink): PX4's own and the ones it sends to."""
    return {
        "offboard_local": 14580 + n, "offboard_remote": 14540 + n,  # the app (mavsdk udpin)
        "gcs_local": 18570 + n,
        "payload_local": 14280 + n, "gimbal_local": 13030 + n,
        "sih_local": 19450 + n, "sih_remote": 19410 + n,  # SIH's display link: ground truth
    }


def find_sitl_dir(explicit: str | Path | None = None, configured: str = "") -> Path:
    """PX4 SITL folder: a command-line flag, else the config's px4.sitl_dir, else $PX4_SITL_DIR."""
    for source, value in (("--px4-dir", explicit), ("px4.sitl_dir", configured), (ENV_VAR, os.environ.get(ENV_VAR))):
        if value:
            d = Path(value).expanduser()
            why = sitl_problem(d)
            if why:
                raise PX4SitlError(f"{source} = {value}: {why}")
            return d.resolve()
    raise PX4SitlError(f"no PX4 SITL build: set {ENV_VAR} (a folder with bin/px4 and etc/), px4.sitl_dir, "
                       f"or --px4-dir; see docs/px4.md")


def sitl_problem(d: Path) -> str | None:
    """None if ``d`` looks like a PX4 SITL build, else why not."""
    px4 = d / "bin" / "px4"
    if not px4.is_file():
        return f"no PX4 binary at {px4}"
    if not os.access(px4, os.X_OK):
        return f"{px4} is not executable"
    if not (d / "etc" / "init.d-posix" / "rcS").is_file():
        return f"no start-up scripts at {d / 'etc' / 'init.d-posix' / 'rcS'}"
    return None


def client_bin(sitl: Path) -> Path:
    """A folder with ``px4`` and its client commands (``px4-param``, ...) as executables.

    PX4's start-up script runs the client commands from the folder of the ``px4`` it was started as.
    A build copied without its symlinks has them as small non-executable text files; then we make a
    folder of symlinks (once per build, in the temp folder) and start PX4 from there.
    """
    b = sitl / "bin"
    probe = b / "px4-param"
    if probe.exists() and os.access(probe, os.X_OK):
        return b
    key = hashlib.sha1(str(b.resolve()).encode()).hexdigest()[:12]
    out = Path(tempfile.gettempdir()) / f"companion-px4-bin-{os.getuid()}-{key}"
    if (out / "px4-param").exists():
        return out
    tmp = Path(tempfile.mkdtemp(prefix=out.name + ".", dir=out.parent))
    (tmp / "px4").symlink_to(b / "px4")
    for f in b.iterdir():
        if f.name.startswith("px4-") and f.name != "px4-alias.sh":
            (tmp / f.name).symlink_to("px4")
        elif f.name == "px4-alias.sh":
            (tmp / f.name).write_bytes(f.read_bytes())
    try:
        tmp.rename(out)
    except OSError:  # another process made it first
        for f in tmp.iterdir():
            f.unlink()
        tmp.rmdir()
    return out


def _udp_free(port: int) -> bool:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("127.0.0.1", port))
        return True
    except OSError:
        return False
    finally:
        s.close()


def _try_lock(path: Path) -> IO[str] | None:
    f = open(path, "a+")  # noqa: SIM115 (held open as long as the lock is held)
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        return None
    return f


def _px4_lock_free(n: int) -> bool:
    """PX4's own 'server running for instance n' lock (/tmp/px4_lock-n), tested and released at once."""
    p = Path(f"/tmp/px4_lock-{n}")
    if not p.exists():
        return True
    f = _try_lock(p)
    if f is None:
        return False
    f.close()
    return True


def claim_instance(candidates: Iterable[int]) -> tuple[int, IO[str]]:
    """The first instance whose ports and locks are free, with our lock on it (hold the file to keep it)."""
    lockdir = Path(tempfile.gettempdir()) / "companion-px4-locks"
    lockdir.mkdir(exist_ok=True)
    tried = []
    for n in candidates:
        tried.append(n)
        lock = _try_lock(lockdir / f"instance-{n}.lock")
        if lock is None:
            continue
        if _px4_lock_free(n) and all(_udp_free(p) for p in instance_ports(n).values()):
            return n, lock
        lock.close()
    raise PX4SitlError(f"no free PX4 instance among {tried} (ports 14540+N, 14580+N, 18570+N, 19410+N... "
                       f"or a PX4 already running as -i N)")


def die_with_parent() -> None:
    """SIGTERM to this process when its parent dies (Linux prctl PR_SET_PDEATHSIG); a no-op elsewhere."""
    import ctypes

    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)


def px4_params(cfg: Config) -> dict[str, float]:
    """The PX4 parameters a run sets: the SIH vehicle (px4.sih), EKF2_GPS_DELAY 0 (SIH's GPS has no delay;
    EKF2's default 110 ms puts its position 1.4-1.9 m ahead at a gate), MPC_THR_HOVER = airframe.hover_thrust
    (PX4's hover-thrust estimate is clamped to it +- 0.2), then px4.params."""
    return {**cfg.px4.sih.params(), "EKF2_GPS_DELAY": 0.0, "MPC_THR_HOVER": cfg.airframe.hover_thrust,
            **cfg.px4.params}


def _fmt_value(v: float) -> str:
    # PX4's `param set` parses by the parameter's type: integers must not carry a decimal point.
    return str(int(v)) if float(v).is_integer() else repr(float(v))


OWNER_FILE = ".companion-owner"  # pid of the process that made a px4-N-* working folder


def clean_stale_work(parent: Path) -> list[Path]:
    """Remove the px4-N-* working folders we made whose process is gone and that hold no ULog (a start that
    was interrupted, ~4 MB each); a folder with a ULog is a flight's record and stays, and a folder without
    our owner file is not ours. Returns the folders removed."""
    removed = []
    for d in parent.glob("px4-*-*"):
        try:
            pid = int((d / OWNER_FILE).read_text().strip())
        except (OSError, ValueError):
            continue
        if _alive(pid) or any((d / "log").glob("*/*.ulg")):
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, not ours to signal
    return True


class PX4Sitl:
    """One PX4 SITL SIH instance in a fresh working folder."""

    def __init__(
        self,
        sitl_dir: Path,
        *,
        instance: int | None = None,
        candidates: Iterable[int] = range(10),
        work_parent: str | Path | None = None,
        params: dict[str, float] | None = None,
        truth_rate: float = 50.0,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.sitl = Path(sitl_dir)
        self.bin = client_bin(self.sitl)
        self.requested = instance
        self.candidates = list(candidates)
        self.work_parent = Path(work_parent) if work_parent else Path(tempfile.gettempdir())
        self.params = dict(params or {})
        self.truth_rate = truth_rate
        self.log = log or (lambda _m: None)
        self.instance: int = -1
        self.work: Path | None = None
        self.proc: subprocess.Popen[bytes] | None = None
        self._lock: IO[str] | None = None
        self._out: IO[bytes] | None = None
        self.origin: tuple[float, float, float] | None = None
        self.t_start = 0.0

    @classmethod
    def from_config(cls, cfg: Config, *, sitl_dir: str | Path | None = None, instance: int | None = None,
                    log: Callable[[str], None] | None = None) -> PX4Sitl:
        """PX4 for this config: its SIH vehicle and parameters (:func:`px4_params`)."""
        p = cfg.px4
        params = px4_params(cfg)
        inst = instance if instance is not None else p.instance
        return cls(find_sitl_dir(sitl_dir, p.sitl_dir), instance=inst,
                   candidates=range(p.instance_min, p.instance_max + 1), work_parent=p.work_dir or None,
                   params=params, truth_rate=p.truth_rate, log=log)

    # ------------------------------------------------------------------------------ addresses
    @property
    def offboard_url(self) -> str:
        """mavsdk URL of the offboard link (PX4 sends to 14540+N)."""
        return f"udpin://127.0.0.1:{14540 + self.instance}"

    @property
    def truth_url(self) -> str:
        """pymavlink URL of SIH's display link, which carries HIL_STATE_QUATERNION (ground truth)."""
        return f"udpin:127.0.0.1:{19410 + self.instance}"

    @property
    def console(self) -> Path:
        assert self.work is not None
        return self.work / "px4.out"

    def ulog_paths(self) -> list[Path]:
        """PX4's own flight logs (ULog) of this run."""
        if self.work is None:
            return []
        return sorted((self.work / "log").glob("*/*.ulg"))

    def config_overrides(self) -> list[str]:
        """``--set`` values that point the app at this PX4 (link, ground truth)."""
        # PX4 SITL instance N is MAVLink system N + 1 (MAV_SYS_ID); the link accepts only link.system_id.
        ov = [f"link.url={self.offboard_url}", f"link.system_id={self.instance + 1}", f"px4.truth_url={self.truth_url}"]
        if self.origin is not None:
            ov.append(f"px4.truth_origin=[{self.origin[0]!r}, {self.origin[1]!r}, {self.origin[2]!r}]")
        return ov

    # ------------------------------------------------------------------------------ life cycle
    def start(self, timeout: float = 60.0) -> PX4Sitl:
        """Start PX4 and apply the parameters; returns once its start-up script has run."""
        cands = [self.requested] if self.requested is not None else self.candidates
        self.instance, self._lock = claim_instance(cands)
        self.work_parent.mkdir(parents=True, exist_ok=True)
        clean_stale_work(self.work_parent)
        self.work = Path(tempfile.mkdtemp(prefix=f"px4-{self.instance}-", dir=self.work_parent))
        (self.work / OWNER_FILE).write_text(f"{os.getpid()}\n")
        env = {k: v for k, v in os.environ.items() if not k.startswith("PX4_")}
        env.update(PX4_SIM_MODEL="sihsim_quadx", PX4_SIMULATOR="sihsim", PX4_SIM_SPEED_FACTOR="1")
        cmd = [str(self.bin / "px4"), "-d", "-w", str(self.work), "-i", str(self.instance), str(self.sitl / "etc")]
        try:
            self._out = open(self.console, "wb")  # noqa: SIM115 (PX4's console, kept beside its logs)
            self.proc = subprocess.Popen(cmd, cwd=self.work, env=env, stdin=subprocess.DEVNULL, stdout=self._out,
                                         stderr=subprocess.STDOUT, start_new_session=True,
                                         preexec_fn=die_with_parent)
            self.t_start = time.monotonic()
            atexit.register(self.stop)
            self.log(f"PX4 SITL instance {self.instance} (pid {self.proc.pid}), working folder {self.work}")
            self._wait_console("Startup script returned", timeout)
            if "Startup script returned successfully" not in self._console_text():
                raise PX4SitlError(f"PX4 start-up script failed; see {self.console}")
            for name, value in self.params.items():
                self.param_set(name, value)
            # Ground truth on SIH's own link, and none of its 200 Hz actuator stream we do not read.
            port = str(19450 + self.instance)
            self.client("mavlink", "stream", "-u", port, "-s", "HIL_STATE_QUATERNION", "-r", _fmt_value(
                self.truth_rate))
            self.client("mavlink", "stream", "-u", port, "-s", "HIL_ACTUATOR_CONTROLS", "-r", "0")
            self.origin = (self.param_get("SIH_LOC_LAT0"), self.param_get("SIH_LOC_LON0"),
                           self.param_get("SIH_LOC_H0"))
        except BaseException as e:
            self.stop()
            if not isinstance(e, PX4SitlError):  # interrupted (Ctrl-C, a signal, a crash): nothing worth keeping
                shutil.rmtree(self.work, ignore_errors=True)  # (a PX4SitlError points at px4.out in it: kept)
            raise
        return self

    def wait_preflight(self, timeout: float = 120.0, passes: int = 1) -> float:
        """Block until PX4's pre-flight checks pass (it would arm now) ``passes`` times in a row, 2 s apart.
        Returns the seconds since start."""
        deadline = time.monotonic() + timeout
        last = ""
        ok = 0
        while time.monotonic() < deadline:
            self._check_alive()
            last = self.client("commander", "check", check=False).strip()
            ok = ok + 1 if "Preflight check: OK" in last else 0
            if ok >= passes:
                return time.monotonic() - self.t_start
            time.sleep(2.0)
        raise PX4SitlError(f"PX4 instance {self.instance}: pre-flight checks did not pass within {timeout:.0f} s "
                           f"({last.splitlines()[-1] if last else 'no answer'}); see {self.console}")

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM (PX4 closes its ULog), SIGKILL after ``timeout``; releases the instance."""
        with contextlib.suppress(Exception):
            atexit.unregister(self.stop)
        p = self.proc
        if p is not None and p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
            try:
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=timeout)
        if self._out is not None:
            self._out.close()
            self._out = None
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def __enter__(self) -> PX4Sitl:
        if self.proc is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------------------ PX4 shell
    def client(self, command: str, *args: str, timeout: float = 10.0, check: bool = True) -> str:
        """Run one of PX4's client commands (``param``, ``commander``, ``mavlink``, ...) against this instance."""
        assert self.work is not None
        exe = self.bin / f"px4-{command}"
        try:
            r = subprocess.run([str(exe), "--instance", str(self.instance), *args], cwd=self.work,
                               capture_output=True, timeout=timeout, check=False)
        except subprocess.TimeoutExpired:
            raise PX4SitlError(f"PX4 instance {self.instance}: `{command} {' '.join(args)}` did not return "
                               f"within {timeout:.0f} s") from None
        out = (r.stdout + r.stderr).decode(errors="replace")
        if check and (r.returncode != 0 or "ERROR" in out):
            raise PX4SitlError(f"PX4 instance {self.instance}: `{command} {' '.join(args)}` failed: "
                               f"{out.strip().splitlines()[-1] if out.strip() else r.returncode}")
        return out

    def param_set(self, name: str, value: float) -> None:
        self.client("param", "set", name, _fmt_value(value))

    def param_get(self, name: str) -> float:
        out = self.client("param", "show", name)
        m = re.search(rf"\b{re.escape(name)}\s*\[[^\]]*\]\s*:\s*([-+0-9.eE]+)", out)
        if m is None:
            raise PX4SitlError(f"PX4 instance {self.instance}: no parameter {name}")
        return float(m.group(1))

    def status(self) -> PX4Status:
        """Armed state, navigation mode and failsafe flag from PX4's commander (no MAVLink needed)."""
        out = self.client("commander", "status")
        mode = re.search(r"\bnavigation mode: (.+)", out)
        fs = re.search(r"in failsafe: (\w+)", out)
        return PX4Status(armed="Armed" in re.findall(r"\b(Armed|Disarmed)\b", out),
                         nav_mode=mode.group(1).strip() if mode else "?",
                         failsafe=bool(fs and fs.group(1) == "yes"))

    def land_and_reset(self, timeout: float = 90.0) -> None:
        """Bring a shared instance back to the start: landed, disarmed, in Hold, pre-flight checks passing.

        After an offboard-loss landing PX4 stays disarmed in Offboard and refuses its pre-flight checks
        until another mode is set; Hold is set here.
        """
        deadline = time.monotonic() + timeout
        st = self.status()
        if st.armed and st.nav_mode != "Land":
            self.client("commander", "land", check=False)
        while self.status().armed:
            if time.monotonic() > deadline:
                raise PX4SitlError(f"PX4 instance {self.instance}: still armed {timeout:.0f} s after land")
            time.sleep(1.0)
        if self.status().nav_mode != "Hold":
            self.client("commander", "mode", "auto:loiter", check=False)
        # Twice, 2 s apart: after a landing PX4's "height estimate not stable" comes and goes, and one passing
        # check was followed by "Arming denied: Resolve system health failures first" (CI, 2026-12-06, loaded).
        self.wait_preflight(max(10.0, deadline - time.monotonic()), passes=2)

    def console_tail(self, lines: int = 8) -> str:
        """The last lines PX4 printed, joined by " | " (for error messages)."""
        return " | ".join(self._console_text().strip().splitlines()[-lines:])

    # ------------------------------------------------------------------------------ helpers
    def _console_text(self) -> str:
        try:
            return self.console.read_text(errors="replace")
        except OSError:
            return ""

    def _check_alive(self) -> None:
        if self.proc is not None and self.proc.poll() is not None:
            tail = self._console_text().strip().splitlines()[-3:]
            raise PX4SitlError(f"PX4 instance {self.instance} exited with {self.proc.returncode}: "
                               f"{' | '.join(tail)} (console {self.console})")

    def _wait_console(self, text: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while text not in self._console_text():
            self._check_alive()
            if time.monotonic() > deadline:
                raise PX4SitlError(f"PX4 instance {self.instance}: no '{text}' within {timeout:.0f} s; "
                                   f"see {self.console}")
            time.sleep(0.2)
