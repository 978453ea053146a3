"""The Ray side of a distributed run: Ray started (or joined), the actors, and the rollout
actors' calls in flight, failures and restarts. What they are asked to collect is the
collection's (distributed/offpolicy.py, distributed/onpolicy.py)."""

from __future__ import annotations

import contextlib
import math
import os
import re
import signal
import socket
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from relayrl.config import Config, to_dict
from relayrl.config_checks import RAY_ADDRESS
from relayrl.distributed.workers import DriverHome, EvalWorker, actor_name
from relayrl.errors import UserError
from relayrl.training.report import plural
from relayrl.training.variables import VariableContainer

# An actor Ray reports unavailable (restarting after a crash, or its connection lost) is asked
# again every RETRY_S; this many such answers in a row count as a second failure.
RETRY_S = 0.2
UNAVAILABLE_LIMIT = 150
WAIT_SAY_S = 30.0  # while actors are not yet placed, a line this often
# A local Ray instance runs at most max(LOCAL_ACTORS_MIN, LOCAL_ACTORS_PER_CORE x usable cores) rollout actors.
LOCAL_ACTORS_MIN = 16
LOCAL_ACTORS_PER_CORE = 8


def init_ray(ray: Any, config: Config) -> None:
    """Join distributed.address, or start a local Ray instance with room for every actor."""
    if ray.is_initialized():
        return
    on_sigterm = signal.getsignal(signal.SIGTERM)
    try:
        _init(ray, config)
    except SystemExit as e:
        # Ray's own SIGTERM handler, in place during ray.init, exits with the signal's number:
        # the CLI's (stop like Ctrl-C, exit 143 with its line) takes the signal instead.
        if e.code != signal.SIGTERM or not callable(on_sigterm):
            raise
        signal.signal(signal.SIGTERM, on_sigterm)
        signal.raise_signal(signal.SIGTERM)
        raise
    finally:
        if callable(on_sigterm):
            # Ray's core replaces SIGTERM's handler in the driver with one that dumps a stack and
            # exits; the CLI's goes back.
            signal.signal(signal.SIGTERM, on_sigterm)


def _init(ray: Any, config: Config) -> None:
    d = config.distributed
    kw: dict[str, Any] = {"include_dashboard": False, "logging_level": "ERROR"}
    if d.address:
        no_head = (f"no Ray cluster answers at distributed.address={d.address!r}: start one (`ray start --head` on "
                   "its head node), or leave distributed.address empty to start a local Ray instance")
        if d.address == "auto" and not os.environ.get("RAY_ADDRESS") and (stale := _stale_cluster()):
            raise UserError(f"distributed.address='auto' joins the cluster {stale}; or start a Ray head (`ray "
                            "start --head`), or leave distributed.address empty for a local Ray instance")
        # host:port (auto: RAY_ADDRESS's where it names one): a head that is not there is waited for at length
        target = os.environ.get("RAY_ADDRESS", "") if d.address == "auto" else d.address
        if re.fullmatch(RAY_ADDRESS, target):
            host, port = target.removeprefix("ray://").rsplit(":", 1)
            via = f" (RAY_ADDRESS={target!r})" if target != d.address else ""
            try:
                grpc = speaks_http2(host.strip("[]"), int(port))  # [::1]: IPv6
            except OSError as e:
                raise UserError(f"{no_head}{via} ({e.strerror or e})") from None
            if grpc is False:  # Ray would retry it for minutes
                raise UserError(f"something answers at distributed.address={d.address!r}{via}, but not as a Ray "
                                "head does (no gRPC): another service's port (the dashboard's, 8265)? A Ray head "
                                "listens on 6379 unless `ray start --head --port` said otherwise")
        try:
            ray.init(address=d.address, **kw)
        except ConnectionError as e:
            if d.address == "auto":
                raise UserError(no_head) from None
            reason = (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
            token = "" if os.environ.get("RAY_AUTH_MODE") else (
                ", and, where it uses token authentication (as `ray start --head` does once ~/.ray/auth_token "
                "exists), that RAY_AUTH_MODE=token is set here")
            client = "" if d.address.startswith("ray://") else "; a Ray Client server (port 10001) takes ray://HOST:PORT"
            raise UserError(f"something answers at distributed.address={d.address!r}, but Ray could not join it "
                            f"({reason}): check that it is a Ray head of Ray {ray.__version__}{token}"
                            f"{client}") from None
    else:
        cores = os.cpu_count() or 1
        # each actor is a process holding torch (~0.3 GB): thousands on one machine exhaust its memory
        # (with RAY_ADDRESS set, Ray joins that cluster instead, and says so below)
        usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores  # (macOS has none)
        most = max(LOCAL_ACTORS_MIN, LOCAL_ACTORS_PER_CORE * usable)
        if d.num_actors > most and not os.environ.get("RAY_ADDRESS"):
            raise UserError(f"distributed.num_actors={d.num_actors:,} starts as many worker processes on this "
                            f"machine (a local Ray instance); at most {most:,} here: join a Ray "
                            "cluster (distributed.address) for more")
        try:
            ray.init(num_cpus=max(cores, math.ceil(d.num_actors * d.actor_cpus) + 1), **kw)
        except ValueError as e:  # Ray joined a cluster RAY_ADDRESS names, which takes no num_cpus
            if "existing cluster" not in str(e):
                raise
            # Ray refuses num_cpus for RAY_ADDRESS before it tries to reach it: a cluster is named, not found
            named = os.environ.get("RAY_ADDRESS")
            if not named and (stale := _stale_cluster()):  # Ray would join it, and `auto` wait for it at length
                raise UserError(f"distributed.address is empty (a local Ray instance of the run's own), but Ray "
                                f"joins the cluster {stale}") from None
            where, other = (f"RAY_ADDRESS={named!r} names a Ray cluster to join", "unset RAY_ADDRESS") if named else \
                ("a Ray cluster is running on this machine", "stop it (ray stop)")
            raise UserError(f"{where}, and distributed.address is empty (a local Ray instance of the run's own): "
                            f"set distributed.address=auto to join that cluster, or {other}") from None


def _stale_cluster() -> str | None:
    """Where the address of this machine's latest cluster, which Ray joins for an empty or `auto`
    address, answers nothing (a head killed without `ray stop`, whose file stays): what to say
    of it and what to do; None where it answers or there is none. Ray's own rule finds the file:
    RAY_TMPDIR, else TMPDIR on Linux, else /tmp; ray/ray_current_cluster in it."""
    linux = sys.platform.startswith("linux")
    root = os.environ.get("RAY_TMPDIR") or (os.environ.get("TMPDIR") if linux else None) or (
        "/tmp" if linux or sys.platform == "darwin" else tempfile.gettempdir())
    file = Path(root) / "ray" / "ray_current_cluster"
    try:
        address = file.read_text().strip()
    except OSError:
        return None
    if not re.fullmatch(RAY_ADDRESS, address):
        return None
    host, port = address.rsplit(":", 1)
    try:
        speaks_http2(host.strip("[]"), int(port), timeout=2.0)
    except OSError:
        return (f"that Ray's file {str(file)!r} names ({address}), where nothing answers: a head stopped without "
                "`ray stop` leaves it; `ray stop --force` clears it")
    return None


# HTTP/2's client preface and an empty SETTINGS frame (length 0, type 4, no flags, stream 0)
HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"


def speaks_http2(host: str, port: int, timeout: float = 5.0) -> bool | None:
    """Whether what listens at host:port answers HTTP/2's connection preface with a SETTINGS
    frame, as gRPC servers (a Ray head's GCS, a Ray Client server) do; None where it says
    nothing within `timeout` (TLS, RAY_USE_TLS: not asked). OSError where nothing listens."""
    with socket.create_connection((host, port), timeout=timeout) as conn:
        if os.environ.get("RAY_USE_TLS", "0").strip().lower() in ("1", "true"):
            return None
        conn.sendall(HTTP2_PREFACE)
        header = b""
        try:
            while len(header) < 4 and (more := conn.recv(4 - len(header))):
                header += more
        except TimeoutError:
            return None
        except OSError:  # reset: not HTTP/2
            return False
    if header[:1] == b"\x15":  # a TLS alert: a head that takes TLS (RAY_USE_TLS unset here), which Ray says itself
        return None
    return len(header) == 4 and header[3] == 0x04  # frame type SETTINGS


class ActorPool:
    """The actors and their collect calls in flight. An actor that fails is restarted by Ray up
    to distributed.max_restarts times, then counted dead."""

    def __init__(self, ray: Any, config: Config, say: Callable[[str], None]) -> None:
        self.ray, self.config, self.say = ray, config, say
        k = self.num_actors = config.distributed.num_actors
        self.failures = [0] * k
        self.unavailable = [0] * k  # ActorUnavailableError answers in a row
        self.tokens: list[str | None] = [None] * k  # each actor's incarnation, from its last answer
        self.restart_counted = [False] * k  # this spell of "unavailable" already counted a restart
        self.retry_at = [0.0] * k  # monotonic time before which actor i is not asked again
        self.restarting: set[int] = set()
        self.dead: set[int] = set()
        self.inflight: dict[Any, tuple[int, int]] = {}  # collect call -> (actor, env steps asked)
        self.workers: list[Any] = []
        self.eval_workers: list[Any] = []
        self.server: Any = None
        self.variables: Any = None
        self.owns_ray = False

    def start(self, worker_class: type, server: Callable[[Any, str], Any] | None) -> None:
        """Ray, the replay server (`server(ray, name)`, where the collection has one) and every
        actor; env errors surface here."""
        ray, c, d = self.ray, self.config, self.config.distributed
        # Owned from before ray.init: a Ctrl-C inside it leaves the processes it started, which
        # `close` shuts down.
        self.owns_ray = not ray.is_initialized()
        if self.owns_ray:  # seconds, tens of them on a busy machine, with nothing else to show meanwhile
            where = f"joining the Ray cluster at {d.address!r}" if d.address else "starting a local Ray instance"
            evals = f" and {plural(d.num_eval_actors, 'eval actor')}" if d.num_eval_actors else ""
            self.say(f"{where}, then {plural(self.num_actors, 'rollout actor')}{evals}")
        elif d.address:  # a Ray Tune trial's, or the user's own ray.init(): its cluster is the one there is
            self.say(f"distributed.address={d.address!r} is not joined: Ray is running in this process already "
                     "(ray.init was called), and the run's actors go on that instance")
        init_ray(ray, c)
        cfg, home = to_dict(c), DriverHome.of(c.env.id)
        # Restartable actors find the server and the container by name: Ray cannot promise to
        # keep actor handles passed as constructor arguments alive for a restart.
        names = f"relayrl-{uuid.uuid4().hex[:12]}"
        self.server = server(ray, actor_name(names, "replay")) if server is not None else None
        self.variables = ray.remote(num_cpus=0, max_concurrency=self.num_actors + 8)(VariableContainer).options(
            name=actor_name(names, "variables")).remote(copy=True)
        worker = ray.remote(num_cpus=d.actor_cpus, max_restarts=d.max_restarts, max_task_retries=0)(worker_class)
        self.workers = [worker.remote(cfg, i, names, home) for i in range(self.num_actors)]
        evaluator = ray.remote(num_cpus=0, max_restarts=d.max_restarts, max_task_retries=0)(EvalWorker)
        self.eval_workers = [evaluator.remote(cfg, names, home) for _ in range(d.num_eval_actors)]
        self.wait_started([w.pid.remote() for w in self.workers + self.eval_workers])

    def wait_started(self, calls: list[Any]) -> None:
        """Wait for every actor's first answer, saying every WAIT_SAY_S what is still waited for
        (a cluster without free CPUs places them only when some come free); an actor that fails
        to start on a worker (its env, its module) is one line."""
        ray, d = self.ray, self.config.distributed
        biggest = max((n.get("Resources", {}).get("CPU", 0.0) for n in ray.nodes() if n.get("Alive")), default=0.0)
        if d.actor_cpus > biggest:  # an actor takes its CPUs on one node
            self.say(f"no node of the Ray cluster has {d.actor_cpus:g} CPUs (the largest has {biggest:g}): the "
                     "rollout actors start only once a node that large joins (an autoscaling cluster adds one); a "
                     "lower distributed.actor_cpus starts them now")
        pending = calls
        while pending:
            _, pending = ray.wait(pending, num_returns=len(pending), timeout=WAIT_SAY_S)
            if pending:
                free, total = ray.available_resources().get("CPU", 0), ray.cluster_resources().get("CPU", 0)
                started = len([call for call in calls[:self.num_actors] if call not in pending])  # rollout actors first
                holds = "holds" if started == 1 else "hold"
                held = f"; this run's {plural(started, 'started rollout actor')} {holds} {started * d.actor_cpus:g}" \
                    if started else ""
                self.say(f"waiting for {plural(len(pending), 'actor')} to start: rollout actors ask for "
                         f"{d.actor_cpus:g} CPU each (distributed.actor_cpus), the Ray cluster has {free:g} of "
                         f"{total:g} CPUs free{held}")
        try:
            ray.get(calls)
        except ray.exceptions.RayActorError as e:
            # the worker's own last line: relayrl's refusal, else the exception that stopped the
            # actor's creation (an env that fails to build there)
            found = (re.findall(r"^relayrl\.errors\.\w+: (.+)$", str(e), flags=re.MULTILINE)
                     or re.findall(r"^((?:\w+\.)*\w*(?:Error|Exception)\w*: .+)$", str(e), flags=re.MULTILINE))
            if not found:
                raise
            raise UserError(f"an actor could not start on a Ray worker: {found[-1]}") from None

    def halt_rollouts(self) -> None:
        """End the rollout actors and forget their calls, so that a run that stops early saves at
        one env step; the eval actors and the replay server stay for its final evaluation and
        save, the server's intake closed."""
        self._kill(self.workers)
        self.inflight.clear()
        if self.server is not None:
            self.ray.get(self.server.close_intake.remote())

    def close(self) -> None:
        """Stop every actor (and the local Ray instance this run started, also one whose start
        was interrupted): no orphan processes."""
        if self.ray.is_initialized():
            self._kill([*self.workers, *self.eval_workers, self.server, self.variables])
        if self.owns_ray:
            self.owns_ray = False
            self.ray.shutdown()

    def _kill(self, handles: list[Any]) -> None:
        for handle in handles:
            if handle is not None:
                with contextlib.suppress(Exception):  # already gone
                    self.ray.kill(handle, no_restart=True)

    @property
    def alive(self) -> int:
        return self.num_actors - len(self.dead)

    def postfix(self) -> dict[str, str]:
        return {"actors": f"{self.alive - len(self.restarting)}/{self.num_actors}"}

    def may_ask(self, i: int) -> bool:
        return i not in self.dead and time.monotonic() >= self.retry_at[i]

    def ask(self, i: int, steps: int, *args: Any) -> Any:
        """Queue `collect(*args)` on actor i, counted as `steps` env steps asked."""
        ref = self.workers[i].collect.remote(*args)
        self.inflight[ref] = (i, steps)
        return ref

    def asked(self) -> int:
        """Env steps the calls in flight ask for."""
        return sum(n for _, n in self.inflight.values())

    def retry_pending(self) -> bool:
        now = time.monotonic()
        return any(i not in self.dead and now < self.retry_at[i] for i in range(self.num_actors))

    def wait(self, also: list[Any], timeout: float) -> None:
        """Sleep until a call in flight (or one of `also`) answers, or `timeout` passes."""
        waiting = [*self.inflight, *also]
        if waiting:
            self.ray.wait(waiting, num_returns=1, timeout=timeout)
        else:
            time.sleep(RETRY_S)  # only an actor waiting to be asked again

    def poll(self, take: Callable[[int, dict[str, Any]], None], dropped: Callable[[int], None] = lambda i: None
             ) -> bool:
        """Hand each call that answered to `take(actor, result)`, in arrival order, once it has
        left the calls in flight; `dropped(actor)` after a failure dropped an actor's calls (their
        steps are free to ask again). True when any call answered."""
        ray = self.ray
        if not self.inflight:
            return False
        ready, _ = ray.wait(list(self.inflight), num_returns=len(self.inflight), timeout=0)
        for ref in ready:
            if ref not in self.inflight:  # dropped with its actor's failure below
                continue
            i, _ = self.inflight.pop(ref)
            try:
                r = ray.get(ref)
            except getattr(ray.exceptions, "ActorUnavailableError", ()) as e:  # Ray >= 2.2x; maybe not a death
                self._on_unavailable(i, e)
                dropped(i)
                continue
            except ray.exceptions.RayActorError as e:
                self._on_death(i, e)
                dropped(i)
                continue
            self.unavailable[i] = 0
            if self.tokens[i] is not None and r["token"] != self.tokens[i] and not self.restart_counted[i]:
                # A new incarnation that no failed call announced: it crashed while idle.
                self._count_restart(i, "it crashed")
            self.tokens[i] = r["token"]
            self.restart_counted[i] = False
            self.restarting.discard(i)
            take(i, r)
        return bool(ready)

    def _drop_calls(self, i: int) -> None:
        """Forget actor i's calls in flight (queued behind the one that failed: they fail too)."""
        for ref in [r for r, (j, _) in self.inflight.items() if j == i]:
            del self.inflight[ref]

    def _on_unavailable(self, i: int, error: Exception) -> None:
        # Ray says the actor may come back: it crashed and Ray is restarting it, or the
        # connection dropped. Count one restart for the whole spell (its queued calls and
        # those sent while it restarts fail the same way, and one crash must not use up every
        # restart) and ask again every RETRY_S until it answers; UNAVAILABLE_LIMIT answers in
        # a row count as a death of their own.
        self.unavailable[i] += 1
        if self.unavailable[i] > UNAVAILABLE_LIMIT:
            self.unavailable[i] = 0
            self._on_death(i, error)
            return
        self._drop_calls(i)
        self.restarting.add(i)
        self.retry_at[i] = time.monotonic() + RETRY_S
        if not self.restart_counted[i]:
            self.restart_counted[i] = True
            self._count_restart(i, type(error).__name__)

    def _on_death(self, i: int, error: Exception) -> None:
        self._drop_calls(i)
        self.tokens[i] = None  # its next incarnation is this restart, counted here
        self._count_restart(i, type(error).__name__)

    def _count_restart(self, i: int, why: str) -> None:
        d = self.config.distributed
        self.failures[i] += 1
        if self.failures[i] > d.max_restarts:
            self.dead.add(i)
            self.restarting.discard(i)
            self.say(f"rollout actor {i} died ({why}) and is not restarted again "
                     f"(distributed.max_restarts={d.max_restarts})")
            if len(self.dead) == self.num_actors:
                # One line, not Ray's chained traceback: why each died was said above, and
                # run_to_end adds what the run keeps and how --resume continues it.
                raise UserError(f"every rollout actor died, each past distributed.max_restarts={d.max_restarts} "
                                "(the lines above say why)") from None
            return
        self.restarting.add(i)
        self.say(f"rollout actor {i} died ({why}); Ray restarts it and it goes on from the "
                 f"latest weights (restart {self.failures[i]} of at most {d.max_restarts})")
