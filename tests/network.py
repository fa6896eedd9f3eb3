"""Hosts that are apart, for the tests: one Linux network namespace per role with its own address on a
private subnet (veth pairs to a bridge in a switch namespace), and partitions between them
(nftables rules that drop every packet to and from chosen peers, as a cut cable or a firewall does:
no reset, no error, silence).

Usage::

    with hosts(["replay", "learner", "actor"]) as net:
        proc = start_role(net["actor"], tmp_path, "actor", "gym/pendulum", [...])
        with partition(net["actor"], [net["replay"], net["learner"]]):
            time.sleep(30)

Creating namespaces needs root (CAP_SYS_ADMIN and CAP_NET_ADMIN); :func:`namespaces_available` and
:func:`nft_available` say why not, for a skip.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise OSError(f"ip {' '.join(args)}: {done.stderr.strip()}")


@dataclass(frozen=True)
class Host:
    namespace: str
    address: str


@contextmanager
def hosts(names: list[str]) -> Iterator[dict[str, Host]]:
    """One namespace per name, each with an address on a private /24 and a veth to a bridge in a
    switch namespace (names carry this process's pid, so parallel runs do not collide); all are
    deleted on exit, whatever happened."""
    tag = f"asac{os.getpid() % 100000}"
    subnet = f"10.{100 + os.getpid() % 100}.{os.getpid() // 100 % 250}"
    switch = f"{tag}sw"
    made: list[str] = []
    try:
        ip("netns", "add", switch)
        made.append(switch)
        ip("-n", switch, "link", "add", "br0", "type", "bridge")
        ip("-n", switch, "link", "set", "br0", "up")
        out: dict[str, Host] = {}
        for i, name in enumerate(names, start=1):
            ns, address = f"{tag}{name}", f"{subnet}.{i}"
            ip("netns", "add", ns)
            made.append(ns)
            ip("link", "add", f"{tag}h{i}", "type", "veth", "peer", "name", f"{tag}s{i}")
            ip("link", "set", f"{tag}h{i}", "netns", ns)
            ip("link", "set", f"{tag}s{i}", "netns", switch)
            ip("-n", switch, "link", "set", f"{tag}s{i}", "master", "br0", "up")
            ip("-n", ns, "link", "set", f"{tag}h{i}", "name", "eth0")
            ip("-n", ns, "addr", "add", f"{address}/24", "dev", "eth0")
            ip("-n", ns, "link", "set", "eth0", "up")
            ip("-n", ns, "link", "set", "lo", "up")
            out[name] = Host(ns, address)
        yield out
    finally:
        for ns in reversed(made):  # deleting a namespace deletes its end of each veth, and so the pair
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def namespaces_available() -> str:
    """Empty if this process may create network namespaces, else why not."""
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root (CAP_SYS_ADMIN, CAP_NET_ADMIN)"
    probe = f"asacprobe{os.getpid()}"
    done = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if done.returncode != 0:
        return f"cannot create a network namespace here: {done.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return ""


def nft_available() -> str:
    """Empty if nftables can cut links between the namespaces, else why not (and how to get it)."""
    missing = namespaces_available()
    if missing:
        return missing
    if shutil.which("nft") is None:
        return "nftables is not installed (Debian: apt-get install -y nftables; .ci/run installs it)"
    return ""


def _nft(host: Host, *rule: str) -> None:
    done = subprocess.run(["ip", "netns", "exec", host.namespace, "nft", *rule], capture_output=True, text=True)
    if done.returncode != 0:
        raise OSError(f"nft {' '.join(rule)} in {host.namespace}: {done.stderr.strip()}")


@contextmanager
def partition(host: Host, peers: Sequence[Host]) -> Iterator[None]:
    """Drop every packet between ``host`` and ``peers`` (both ways, silently) until the block ends."""
    addresses = "{ " + ", ".join(p.address for p in peers) + " }"
    _nft(host, "add", "table", "inet", "cut")
    try:
        for chain, hook, field in (("out", "output", "daddr"), ("in", "input", "saddr")):
            _nft(host, "add", "chain", "inet", "cut", chain, f"{{ type filter hook {hook} priority 0 ; }}")
            _nft(host, "add", "rule", "inet", "cut", chain, "ip", field, addresses, "drop")
        yield
    finally:
        _nft(host, "delete", "table", "inet", "cut")


def start_role(
    host: Host, folder: Path, role: str, task: str, args: Sequence[str], env: dict[str, str], log: Path
) -> subprocess.Popen[bytes]:
    """``main_ds.py TASK ROLE ARGS`` inside ``host``, listening on its address only, its run folder
    under ``folder`` (a host's own disk), its output in ``log``."""
    command = ["ip", "netns", "exec", host.namespace, sys.executable, str(ROOT / "main_ds.py"), task, role,
               "--model_root", str(folder), "--override", f"net.bind_host={host.address}", *args]  # fmt: skip
    with log.open("wb") as out:
        return subprocess.Popen(command, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)


@contextmanager
def names(clients: Sequence[Host]) -> Iterator[Callable[[str, Host], None]]:
    """A name that moves between hosts, as a Kubernetes Service's name follows a rescheduled pod:
    yields ``point(name, host)``, which makes ``name`` resolve to ``host``'s address in every one of
    ``clients``. ``ip netns exec`` mounts ``/etc/netns/NS/hosts`` over ``/etc/hosts`` for the process it
    starts, so the files exist before the clients start and are rewritten in place (same inode, which
    the mount shows); they are removed on exit."""
    folders = [Path("/etc/netns") / c.namespace for c in clients]
    entries: dict[str, str] = {}

    def point(name: str, host: Host) -> None:
        entries[name] = host.address
        text = "127.0.0.1 localhost\n" + "".join(f"{address} {n}\n" for n, address in entries.items())
        for folder in folders:
            with (folder / "hosts").open("r+") as hosts_file:
                hosts_file.truncate(0)
                hosts_file.write(text)

    try:
        for folder in folders:
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "hosts").write_text("127.0.0.1 localhost\n")
        yield point
    finally:
        for folder in folders:
            shutil.rmtree(folder, ignore_errors=True)


@contextmanager
def slow_link(host: Host, to: str, delay_ms: float, log: Path, port: int | None = None) -> Iterator[str]:
    """A relay inside ``host`` (tests/relay.py) that holds every byte ``delay_ms`` each way on its way to
    ``to`` (``ADDRESS:PORT``); yields the ``127.0.0.1:PORT`` a process in ``host`` calls instead (``port``:
    that port, e.g. the one a peer announces; else one derived from ``to``'s). The relay is stopped on exit."""
    port = 40000 + int(to.rsplit(":", 1)[1]) % 20000 if port is None else port
    listen = f"127.0.0.1:{port}"  # the namespace's own loopback: its ports
    command = ["ip", "netns", "exec", host.namespace, sys.executable, "-m", "tests.relay", "--listen", listen,
               "--to", to, "--delay-ms", str(delay_ms)]  # fmt: skip
    with log.open("wb") as out:
        relay = subprocess.Popen(command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while "relay listening" not in log.read_text():
            if relay.poll() is not None or time.monotonic() > deadline:
                raise OSError(f"the relay to {to} did not start: {log.read_text()[-2000:]}")
            time.sleep(0.1)
        yield listen
    finally:
        relay.terminate()
        relay.wait(timeout=10)


@contextmanager
def lossy(host: Host, percent: int) -> Iterator[None]:
    """Drop ``percent`` % of ``host``'s TCP packets at random, each way (nftables ``numgen random``)."""
    _nft(host, "add", "table", "inet", "loss")
    try:
        for chain, hook in (("out", "output"), ("in", "input")):
            _nft(host, "add", "chain", "inet", "loss", chain, f"{{ type filter hook {hook} priority 0 ; }}")
            _nft(host, "add", "rule", "inet", "loss", chain, "meta", "l4proto", "tcp", "numgen", "random", "mod",
                 "100", "<", str(percent), "drop")  # fmt: skip
        yield
    finally:
        _nft(host, "delete", "table", "inet", "loss")


@contextmanager
def capped(host: Host, mbit: float) -> Iterator[None]:
    """``host``'s link capped at ``mbit`` Mbit/s in its sending direction (``tc ... tbf`` on its eth0; the
    kernel here has tbf, not netem). What it receives is not shaped: for an actor that is the weights."""
    done = subprocess.run(["ip", "netns", "exec", host.namespace, "tc", "qdisc", "add", "dev", "eth0", "root",
                           "tbf", "rate", f"{mbit}mbit", "burst", "32kb", "latency", "400ms"],
                          capture_output=True, text=True)  # fmt: skip
    if done.returncode != 0:
        raise OSError(f"tc tbf in {host.namespace}: {done.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["ip", "netns", "exec", host.namespace, "tc", "qdisc", "del", "dev", "eth0", "root"],
                       capture_output=True)  # fmt: skip
