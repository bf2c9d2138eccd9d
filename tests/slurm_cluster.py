"""A single-node SLURM cluster on this machine, for the cluster profile's integration test.

Debian's ``slurmctld``, ``slurmd`` and ``munge`` (installed with ``apt-get`` when missing
and the test runs as root), started by hand (no systemd): ``munged --force``, then
``slurmctld -D`` and ``slurmd -D`` as children of the test, with a generated
``/etc/slurm/slurm.conf``: one node (``localhost``, this machine's CPUs and memory), one
partition, ``select/cons_tres`` with cores and memory as consumable resources,
``proctrack/linuxproc``, ``task/none``, no accounting database (so the executor asks
``squeue``, and ``MinJobAge`` keeps finished jobs visible to it for 10 minutes).

:func:`start_cluster` returns a :class:`Cluster` or raises :class:`Unavailable` with the
reason (the test skips with it); :meth:`Cluster.stop` ends only the daemons it started
and removes the configuration it wrote.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

CONF = Path("/etc/slurm/slurm.conf")
#: the first line of a configuration this module wrote (one without it is never touched)
MARKER = "# robo3d test cluster (tests/slurm_cluster.py): safe to delete"
PACKAGES = ("slurmctld", "slurmd", "slurm-client", "munge")
BINARIES = ("slurmctld", "slurmd", "sbatch", "squeue", "sinfo", "munged")
MUNGE_SOCKET = Path("/run/munge/munge.socket.2")


class Unavailable(Exception):
    """SLURM cannot be run here; the message says why."""


def _which(name: str) -> str | None:
    return shutil.which(name) or next(
        (str(p) for d in ("/usr/sbin", "/sbin") if (p := Path(d) / name).exists()), None)


def _running(name: str) -> bool:
    """Whether a live process (not a zombie) has this name."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        comm, state = text[text.index("(") + 1:text.rindex(")")], text[text.rindex(")") + 2]
        if comm == name and state not in "ZX":
            return True
    return False


def install(timeout: float = 400) -> None:
    """Install SLURM and munge with apt-get when a binary is missing (root only)."""
    if all(_which(b) for b in BINARIES):
        return
    if os.geteuid() != 0:
        raise Unavailable("SLURM is not installed and the test is not root (apt-get "
                          f"install {' '.join(PACKAGES)} needs root)")
    if not shutil.which("apt-get"):
        raise Unavailable("SLURM is not installed and there is no apt-get here")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    cmd = ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *PACKAGES]
    try:
        if subprocess.run(cmd, env=env, capture_output=True, timeout=timeout).returncode:
            subprocess.run(["apt-get", "update", "-qq"], env=env, capture_output=True,
                           timeout=timeout, check=True)
            subprocess.run(cmd, env=env, capture_output=True, timeout=timeout, check=True)
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as exc:
        err = getattr(exc, "stderr", b"") or b""
        raise Unavailable(f"apt-get could not install {' '.join(PACKAGES)}: "
                          f"{err.decode(errors='replace').strip()[-300:] or exc}") from exc
    missing = [b for b in BINARIES if not _which(b)]
    if missing:
        raise Unavailable(f"installed {' '.join(PACKAGES)} but {', '.join(missing)} missing")


def memory_mb() -> int:
    """This machine's physical memory, MB."""
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2**20


def write_config(state: Path, cpus: int, mem_mb: int) -> str:
    """The cluster's slurm.conf (written to :data:`CONF`); its text."""
    for d in ("ctld", "d"):
        (state / d).mkdir(parents=True, exist_ok=True)
    text = "\n".join([
        MARKER,
        "ClusterName=robo3dtest",
        "SlurmctldHost=localhost",
        "SlurmUser=root",
        "AuthType=auth/munge",
        f"StateSaveLocation={state / 'ctld'}",
        f"SlurmdSpoolDir={state / 'd'}",
        f"SlurmctldPidFile={state / 'slurmctld.pid'}",
        f"SlurmdPidFile={state / 'slurmd.pid'}",
        f"SlurmctldLogFile={state / 'slurmctld.log'}",
        f"SlurmdLogFile={state / 'slurmd.log'}",
        "SlurmctldPort=6817",
        "SlurmdPort=6818",
        "ProctrackType=proctrack/linuxproc",
        "TaskPlugin=task/none",
        "MpiDefault=none",
        "SchedulerType=sched/backfill",
        "SelectType=select/cons_tres",
        "SelectTypeParameters=CR_Core_Memory",
        "ReturnToService=2",
        "MinJobAge=600",
        "AccountingStorageType=accounting_storage/none",
        "JobAcctGatherType=jobacct_gather/none",
        "JobCompType=jobcomp/none",
        "SlurmdTimeout=60",
        "InactiveLimit=0",
        f"NodeName=localhost CPUs={cpus} RealMemory={mem_mb} State=UNKNOWN",
        "PartitionName=test Nodes=localhost Default=YES MaxTime=INFINITE State=UP",
    ]) + "\n"
    CONF.parent.mkdir(parents=True, exist_ok=True)
    CONF.write_text(text)
    return text


@dataclass
class Cluster:
    """The daemons this test started (and whether it wrote the configuration)."""

    state: Path
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    wrote_conf: bool = False

    def log_tail(self, n: int = 2000) -> str:
        out = []
        for name in ("slurmctld.log", "slurmd.log"):
            f = self.state / name
            if f.exists():
                out.append(f"--- {name}\n{f.read_text(errors='replace')[-n:]}")
        return "\n".join(out)

    def stop(self) -> None:
        """End the daemons it started (slurmd, slurmctld, then munged) and remove its
        configuration."""
        for name in ("slurmd", "slurmctld", "munged"):
            p = self.procs.pop(name, None)
            if p is None:
                continue
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        if self.wrote_conf and CONF.exists() and CONF.read_text().startswith(MARKER):
            CONF.unlink()


def _node_state() -> str:
    proc = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], capture_output=True, text=True,
                          timeout=10)
    return proc.stdout.strip()


def start_cluster(state: Path, cpus: int | None = None, mem_mb: int | None = None,
                  timeout: float = 60) -> Cluster:
    """Install (when needed), configure and start a one-node cluster; wait until its node
    is idle. Raises :class:`Unavailable` with the reason when it cannot."""
    if os.geteuid() != 0:
        raise Unavailable("starting slurmctld, slurmd and munged by hand needs root")
    install()
    if CONF.exists() and not CONF.read_text().startswith(MARKER):
        raise Unavailable(f"{CONF} is there and not the test's: a real cluster's "
                          "configuration is not touched")
    for name in ("slurmctld", "slurmd"):
        if _running(name):
            raise Unavailable(f"a {name} is already running on this machine")
    cluster = Cluster(state)
    try:
        cluster.wrote_conf = True
        write_config(state, cpus or os.cpu_count() or 1,
                     mem_mb or int(memory_mb() * 0.9))
        if not _running("munged"):
            MUNGE_SOCKET.parent.mkdir(parents=True, exist_ok=True)
            cluster.procs["munged"] = subprocess.Popen(
                [_which("munged"), "--force", "--foreground"], stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL)
            t0 = time.monotonic()
            while not MUNGE_SOCKET.exists():
                if cluster.procs["munged"].poll() is not None or time.monotonic() - t0 > 10:
                    raise Unavailable("munged did not start")
                time.sleep(0.1)
        for name in ("slurmctld", "slurmd"):
            log = open(state / f"{name}.out", "w")  # noqa: SIM115 (the daemon's lifetime)
            cluster.procs[name] = subprocess.Popen([_which(name), "-D"], stdout=log,
                                                   stderr=subprocess.STDOUT)
        t0 = time.monotonic()
        while (st := _node_state()) != "idle":
            dead = [n for n, p in cluster.procs.items() if p.poll() is not None]
            if dead or time.monotonic() - t0 > timeout:
                raise Unavailable(f"the node is not idle after {time.monotonic() - t0:.0f} s "
                                  f"(sinfo: {st!r}; exited: {dead or 'none'})\n"
                                  f"{cluster.log_tail()}")
            time.sleep(0.5)
    except BaseException:
        cluster.stop()
        raise
    return cluster
