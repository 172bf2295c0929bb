"""A real single-node Slurm on this machine, for `make test-cluster`: Debian's slurmctld, slurmd,
slurm-client and munge (installed with apt-get when absent and running as root), a slurm.conf for
localhost with this machine's cores and memory, free ports, and everything under one temporary
folder. Job completions go to a text file (jobcomp/filetxt) that `sacct --completion` reads: no
database to run.

    with LocalSlurm() as slurm:   # munged, slurmctld and slurmd started, the node idle
        slurm.run("sbatch", ...)
    # every daemon stopped, even when the block raised

    python tests/cluster/local_slurm.py   # start, show sinfo, stop
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

PACKAGES = ("slurmctld", "slurmd", "slurm-client", "munge")
COMMANDS = ("slurmctld", "slurmd", "sbatch", "munged")


class SlurmUnavailable(RuntimeError):
    """Slurm is not installed and cannot be installed here (not root, or no apt-get)."""


def ensure_installed() -> None:
    """Debian's Slurm and munge packages, installed when a command is missing."""
    missing = [c for c in COMMANDS if shutil.which(c) is None and not Path("/usr/sbin", c).exists()]
    if not missing:
        return
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        raise SlurmUnavailable(f"{', '.join(missing)} missing; installing them needs root and apt-get")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    subprocess.run(["apt-get", "update", "-qq"], check=True, env=env, timeout=300)
    subprocess.run(
        ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *PACKAGES], check=True, env=env, timeout=600
    )


def free_ports(n: int) -> list[int]:
    """n distinct TCP ports free on localhost now (the OS picks them)."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def memory_mb() -> int:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) // 1024
    raise RuntimeError("no MemTotal in /proc/meminfo")


NODE = "wgsnode"
DAEMONS = ("slurmctld", "slurmd", "slurmstepd", "munged")
PR_SET_CHILD_SUBREAPER = 36  # <linux/prctl.h>


def become_subreaper() -> None:
    """Make orphaned descendants (slurmstepd leaves slurmd's process group) this process's children,
    not PID 1's: a container's PID 1 may never reap them, and they would stay as zombies."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER)")


def children() -> dict[int, tuple[str, str]]:
    """This process's children: pid -> (command name, state letter; Z for a zombie)."""
    found = {}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1 : stat.rindex(")")]
        state, ppid = stat[stat.rindex(")") + 2 :].split()[:2]
        if int(ppid) == os.getpid():
            found[int(proc.name)] = (name, state)
    return found


def end_daemon_children(timeout_s: float = 10) -> None:
    """SIGKILL this process's children that are Slurm or munge daemons, and reap them and every
    zombie child."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        left = {pid: s for pid, s in children().items() if s[0] in DAEMONS or s[1] == "Z"}
        if not left:
            return
        for pid, (_, state) in left.items():
            with contextlib.suppress(ProcessLookupError, ChildProcessError):
                if state != "Z":
                    os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, os.WNOHANG)
        time.sleep(0.1)
    raise RuntimeError(f"local slurm: children left after {timeout_s:.0f} s: {children()}")


class LocalSlurm:
    """Start a one-node cluster in a temporary folder; `stop()` (or leaving the `with` block) ends
    every daemon it started and removes the folder (kept where WGS_KEEP_SLURM is set). `env` is what
    a Slurm command needs to reach it (SLURM_CONF)."""

    def __init__(self, cpus: int | None = None, mem_mb: int | None = None, kill_wait_s: int = 30):
        ensure_installed()
        self.dir = Path(tempfile.mkdtemp(prefix="wgs-slurm-"))
        self.cpus = cpus or os.cpu_count() or 1
        self.mem_mb = mem_mb or int(0.8 * memory_mb())
        self.kill_wait_s = kill_wait_s
        self.procs: list[subprocess.Popen] = []
        self.conf = self.dir / "slurm.conf"
        self.jobcomp = self.dir / "jobcomp.txt"
        self.env = {**os.environ, "SLURM_CONF": str(self.conf)}

    # ------------------------------------------------------------------ set-up
    def write_config(self) -> None:
        d = self.dir
        for sub in ("state", "spool", "munge"):
            (d / sub).mkdir(exist_ok=True)
        (d / "munge").chmod(0o700)
        ctld_port, slurmd_port = free_ports(2)
        self.conf.write_text(
            "\n".join(
                [
                    "ClusterName=wgstest",
                    "SlurmctldHost=localhost(127.0.0.1)",
                    f"SlurmctldPort={ctld_port}",
                    f"SlurmdPort={slurmd_port}",
                    "SlurmUser=root",
                    "SlurmdUser=root",
                    "AuthType=auth/munge",
                    "CredType=cred/munge",
                    f"AuthInfo=socket={d / 'munge' / 'munge.socket'}",
                    "MpiDefault=none",
                    # no cgroups in a container: processes tracked through their parents
                    "ProctrackType=proctrack/linuxproc",
                    "TaskPlugin=task/none",
                    "JobAcctGatherType=jobacct_gather/none",
                    "AccountingStorageType=accounting_storage/none",
                    "JobCompType=jobcomp/filetxt",
                    f"JobCompLoc={self.jobcomp}",
                    "SchedulerType=sched/backfill",
                    "SelectType=select/cons_tres",
                    "SelectTypeParameters=CR_Core_Memory",
                    "DefMemPerCPU=2048",  # a job that asks no memory takes 2 GB a core, not the whole node
                    "ReturnToService=2",
                    "MinJobAge=600",
                    f"KillWait={self.kill_wait_s}",
                    "SlurmctldTimeout=30",
                    "SlurmdTimeout=60",
                    f"StateSaveLocation={d / 'state'}",
                    f"SlurmdSpoolDir={d / 'spool'}",
                    f"SlurmctldPidFile={d / 'slurmctld.pid'}",
                    f"SlurmdPidFile={d / 'slurmd.pid'}",
                    f"SlurmctldLogFile={d / 'slurmctld.log'}",
                    f"SlurmdLogFile={d / 'slurmd.log'}",
                    f"NodeName={NODE} NodeHostname={socket.gethostname()} NodeAddr=127.0.0.1 "
                    f"CPUs={self.cpus} RealMemory={self.mem_mb} State=UNKNOWN",
                    "PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
                    "",
                ]
            )
        )

    def _daemon(self, *cmd: str) -> None:
        """A daemon in the foreground of its own process group, its output in the folder."""
        out = open(self.dir / f"{Path(cmd[0]).name}.out", "w")  # noqa: SIM115 - kept for the process's life
        # the daemons read the config from -f: SLURM_CONF in the environment marks only what jobs run
        env = {k: v for k, v in self.env.items() if k != "SLURM_CONF"}
        self.procs.append(subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True))

    def start(self, timeout_s: float = 60) -> LocalSlurm:
        try:
            become_subreaper()
            self.write_config()
            key = self.dir / "munge" / "munge.key"
            key.write_bytes(os.urandom(1024))
            key.chmod(0o400)
            munge = self.dir / "munge"
            self._daemon(
                shutil.which("munged") or "/usr/sbin/munged",
                "--foreground",
                "--force",
                f"--key-file={key}",
                f"--socket={munge / 'munge.socket'}",
                f"--pid-file={munge / 'munged.pid'}",
                f"--log-file={munge / 'munged.log'}",
                f"--seed-file={munge / 'munged.seed'}",
            )
            self._wait(lambda: (munge / "munge.socket").exists(), timeout_s, "munged's socket")
            self._daemon(shutil.which("slurmctld") or "/usr/sbin/slurmctld", "-D", "-i", "-f", str(self.conf))
            self._wait(lambda: self.run("sinfo", check=False).returncode == 0, timeout_s, "slurmctld")
            self._daemon(shutil.which("slurmd") or "/usr/sbin/slurmd", "-D", "-N", NODE, "-f", str(self.conf))
            self._wait(lambda: self.node_state() == "idle", timeout_s, "the node idle in sinfo")
        except BaseException:
            self.stop()
            raise
        return self

    def _wait(self, ready, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not ready():
            dead = [p.args[0] for p in self.procs if p.poll() is not None]
            if dead or time.monotonic() > end:
                found = [f for f in sorted(self.dir.glob("*.*")) if f.suffix in (".out", ".log")]
                logs = "\n".join(f"--- {f.name}\n{f.read_text(errors='replace')[-2000:]}" for f in found)
                raise RuntimeError(f"local slurm: no {what} after {timeout_s:.0f} s (exited: {dead})\n{logs}")
            time.sleep(0.5)

    # ------------------------------------------------------------------ use
    def run(self, *cmd: str, check: bool = True) -> subprocess.CompletedProcess:
        return subprocess.run(cmd, env=self.env, capture_output=True, text=True, check=check, timeout=60)

    def node_state(self) -> str:
        res = self.run("sinfo", "-h", "-N", "-o", "%T", check=False)
        return res.stdout.strip().rstrip("*~#") if res.returncode == 0 else ""

    def completions(self) -> list[dict[str, str]]:
        """Every job record of the completion file, as `sacct --completion` reads it."""
        res = self.run("sacct", "--completion", "-n", "-P", "-o", "jobid,jobname,state,exitcode,elapsed", check=False)
        rows = []
        for line in res.stdout.splitlines():
            parts = line.split("|")
            if len(parts) >= 5:
                rows.append(dict(zip(("jobid", "name", "state", "exitcode", "elapsed"), parts, strict=False)))
        return rows

    # ------------------------------------------------------------------ tear-down
    def stop(self) -> None:
        """Cancel every job, SIGTERM every daemon's process group, SIGKILL what is left, then any
        process of a job (they carry this cluster's SLURM_CONF in their environment), and reap the
        orphans that came back to this process (see `become_subreaper`)."""
        if self.procs and self.procs[-1].poll() is None:
            self.run("scancel", "--full", "--quiet", *self.job_ids(), check=False)
            end = time.monotonic() + 30
            while self.job_ids() and time.monotonic() < end:
                time.sleep(0.5)
        for p in reversed(self.procs):
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, signal.SIGTERM)
        end = time.monotonic() + 20
        for p in self.procs:
            try:
                p.wait(max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(10)
        self.procs.clear()
        for pid in self.job_processes():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
        end_daemon_children()
        if not os.environ.get("WGS_KEEP_SLURM"):  # set it to read the daemons' logs afterwards
            shutil.rmtree(self.dir, ignore_errors=True)

    def job_ids(self) -> list[str]:
        res = self.run("squeue", "-h", "-o", "%i", check=False)
        return res.stdout.split() if res.returncode == 0 else []

    def job_processes(self) -> list[int]:
        """Processes started by this cluster's jobs, or by commands pointed at it."""
        mark = f"SLURM_CONF={self.conf}".encode()
        found = []
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit() or int(proc.name) == os.getpid():
                continue
            try:
                if mark in (proc / "environ").read_bytes().split(b"\0"):
                    found.append(int(proc.name))
            except OSError:
                continue
        return found

    def __enter__(self) -> LocalSlurm:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


if __name__ == "__main__":
    with LocalSlurm() as cluster:
        print(cluster.run("sinfo").stdout)
        print(cluster.run("scontrol", "show", "node").stdout)
