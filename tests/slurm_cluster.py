"""A real SLURM cluster of one node on this machine, for the tests that submit to it (tests/test_slurm.py).

Debian's slurm-wlm 22.05 (slurmctld, slurmd, the client commands) and munge, as ``.ci/run`` installs
them: munged, slurmctld and slurmd run in the foreground under ``local_cluster``, as whoever runs the
tests (root or not), every file of theirs (munge key and socket, slurm.conf, state, spool, logs) in one
folder, on free ports; no cgroups (processes tracked by /proc, no task binding) and no accounting
database. The node offers more CPUs than the machine has (``SlurmdParameters=config_overrides``): four
2-task jobs fit at once, so that only a job array's own limit keeps them from running together.
"""

import contextlib
import ctypes
import getpass
import os
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

COMMANDS = ("munged", "slurmctld", "slurmd", "sbatch", "srun", "squeue", "scancel", "sinfo")
INSTALL = "apt-get install slurmctld slurmd slurm-client munge (.ci/run does)"
PR_SET_PDEATHSIG = 1  # prctl's option (linux/prctl.h): the signal a process gets when its parent ends


def missing() -> str | None:
    """Why no cluster can be started here (the commands that are not installed), or None."""
    if absent := [c for c in COMMANDS if shutil.which(c) is None]:
        return f"{', '.join(absent)} not installed: {INSTALL}"
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def slurm_conf(root: Path, node: str, cpus: int, memory_mb: int, user: str) -> str:
    """slurm.conf of a one-node cluster whose files all lie in ``root`` (a partition ``debug``), its daemons
    run by ``user`` (root or not: the jobs are that user's own)."""
    return "\n".join([
        "ClusterName=nerfexp-test", f"SlurmctldHost={node}(127.0.0.1)", f"SlurmUser={user}", f"SlurmdUser={user}",
        "AuthType=auth/munge", "CredType=cred/munge", f"AuthInfo=socket={root}/run/munge.socket",
        f"SlurmctldPort={free_port()}", f"SlurmdPort={free_port()}",
        f"StateSaveLocation={root}/state", f"SlurmdSpoolDir={root}/spool",
        f"SlurmctldPidFile={root}/run/slurmctld.pid", f"SlurmdPidFile={root}/run/slurmd.pid",
        f"SlurmctldLogFile={root}/log/slurmctld.log", f"SlurmdLogFile={root}/log/slurmd.log",
        "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none", "JobAcctGatherType=jobacct_gather/none",
        "AccountingStorageType=accounting_storage/none", "JobCompType=jobcomp/none", "MpiDefault=none",
        "SchedulerType=sched/backfill", "SelectType=select/cons_tres", "SelectTypeParameters=CR_CPU",
        "ReturnToService=2", "SlurmdParameters=config_overrides", "KillWait=30",
        f"NodeName={node} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={memory_mb} State=UNKNOWN",
        "PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP", "",
    ])


def wait_until(ready, what: str, logs: Path, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        if time.monotonic() > deadline:
            tails = {p.name: p.read_text()[-1500:] for p in sorted(logs.glob("*.log"))}
            raise RuntimeError(f"the local SLURM cluster: {what} not ready after {timeout_s} s; logs: {tails}")
        time.sleep(0.2)


def end_with_parent() -> None:
    """Run in a daemon's process before it starts: Linux sends it SIGTERM when the process that started it
    ends, also where that is killed before it can stop the daemons (a test session ended by SIGTERM)."""
    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def node_idle(env: dict) -> bool:
    state = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, env=env)
    return state.returncode == 0 and state.stdout.strip() == "idle"


@contextlib.contextmanager
def local_cluster(root: Path, cpus: int = 8, memory_mb: int = 8000) -> Iterator[dict]:
    """Start munged, slurmctld and slurmd with their files in ``root``; yield the environment that points
    SLURM's commands at this cluster (``SLURM_CONF``); cancel every job and stop the daemons after."""
    for folder in ("munge", "run", "state", "spool", "log"):
        (root / folder).mkdir(parents=True)
    root.chmod(0o755)
    (root / "munge").chmod(0o700)  # munged refuses a key others could read
    key = root / "munge" / "munge.key"
    key.write_bytes(os.urandom(1024))
    key.chmod(0o400)
    node = socket.gethostname().split(".")[0]
    conf = root / "slurm.conf"
    user = getpass.getuser()
    conf.write_text(slurm_conf(root, node, cpus, memory_mb, user))
    env = {**os.environ, "SLURM_CONF": str(conf)}
    socket_path = root / "run" / "munge.socket"
    logs = root / "log"
    daemons = []

    def start(*argv: str) -> None:  # in the foreground, what it prints besides its log file in log/NAME.out
        with open(logs / f"{argv[0]}.out", "w") as out:
            daemons.append(subprocess.Popen(argv, env=env, stdout=out, stderr=subprocess.STDOUT,
                                            preexec_fn=end_with_parent))

    try:
        start("munged", "--foreground", "--force", f"--key-file={key}", f"--socket={socket_path}",
              f"--pid-file={root}/run/munged.pid", f"--seed-file={root}/munge/seed", f"--log-file={logs}/munged.log")
        wait_until(socket_path.exists, "munged", logs)
        start("slurmctld", "-D", "-c", "-f", str(conf))  # -c: no state from an earlier start
        start("slurmd", "-D", "-f", str(conf))
        wait_until(lambda: node_idle(env), "the node", logs)
        yield env
    finally:
        if len(daemons) == 3:
            subprocess.run(["scancel", "--full", "--user", user], env=env, capture_output=True)
            with contextlib.suppress(RuntimeError):
                wait_until(lambda: not subprocess.run(["squeue", "-h"], capture_output=True, text=True,
                                                      env=env).stdout.strip(), "the cancelled jobs' end", logs, 40)
        for daemon in reversed(daemons):
            daemon.terminate()
            try:
                daemon.wait(timeout=20)
            except subprocess.TimeoutExpired:
                daemon.kill()
