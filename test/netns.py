# Copyright 2026 The mlv_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
Linux network namespaces as "hosts" on one machine, for multi-host tests.

``veth_pair()``: two namespaces joined by a veth pair on one private /24 (two machines on one
LAN). ``routed_pair()``: two namespaces on different /24s joined through a third, forwarding
namespace (two machines on different subnets: unicast is routed, multicast is not).

Names (namespaces, devices) are unique to the call, so concurrent test runs never collide; each
namespace's loopback is brought up; every namespace is deleted on exit, whatever happened
(deleting a namespace destroys the veth ends inside it, and with them the pairs).

Needs root (CAP_SYS_ADMIN and CAP_NET_ADMIN) and iproute2; ``netns_unavailable()`` says why not.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
import json
import secrets
import shutil
import subprocess


@dataclass(frozen=True)
class Host:
    """A host: its namespace, its veth device there, and that device's IPv4 address."""

    ns: str
    dev: str
    ip: str

    def exec_argv(self, *argv: str) -> list[str]:
        """Return ``argv`` run in this namespace (``ip netns exec``: same pid and signals)."""
        return ['ip', 'netns', 'exec', self.ns, *argv]

    def link_stats(self) -> dict:
        """Return the veth's kernel counters: ``rx_bytes``, ``tx_bytes``, ``rx_packets``, ..."""
        out = _ip('-n', self.ns, '-s', '-j', 'link', 'show', 'dev', self.dev)
        stats = json.loads(out)[0]['stats64']
        return {f'{way}_{key}': value for way in ('rx', 'tx') for key, value in stats[way].items()}


def _ip(*args: str) -> str:
    res = subprocess.run(['ip', *args], capture_output=True, text=True, timeout=10)
    if res.returncode != 0:
        raise RuntimeError(f'ip {" ".join(args)}: {res.stderr.strip()}')
    return res.stdout


def netns_unavailable() -> str | None:
    """None if this process may create network namespaces, else the precise reason it may not."""
    if shutil.which('ip') is None:
        return 'iproute2 `ip` is not installed'
    probe = f'mlvprobe{secrets.token_hex(4)}'
    res = subprocess.run(['ip', 'netns', 'add', probe], capture_output=True, text=True, timeout=10)
    if res.returncode != 0:
        return (
            '`ip netns add` is not permitted here (needs root / CAP_SYS_ADMIN): '
            f'{res.stderr.strip()}'
        )
    subprocess.run(['ip', 'netns', 'del', probe], capture_output=True, timeout=10)
    return None


def _new_names() -> tuple[str, int, int]:
    """
    Return a token for unique names and two octets choosing private subnets.

    A token for unique names (6 hex digits keep device names within IFNAMSIZ, 15) and two
    octets choosing private subnets 10.X.Y.0/24 (and 10.X.Y+1.0/24).
    """
    return secrets.token_hex(3), secrets.randbelow(250) + 1, secrets.randbelow(250) + 1


@contextmanager
def _namespaces(names: list[str], devs: list[str]):
    """Create the namespaces; on exit delete them (and any listed device left in ours)."""
    created = []
    try:
        for ns in names:
            _ip('netns', 'add', ns)
            created.append(ns)
            _ip('-n', ns, 'link', 'set', 'lo', 'up')
        yield
    finally:
        for ns in created:
            subprocess.run(['ip', 'netns', 'del', ns], capture_output=True, timeout=10)
        for (
            dev
        ) in devs:  # a veth created but not yet moved (failure in between) lives in our namespace
            subprocess.run(['ip', 'link', 'del', dev], capture_output=True, timeout=10)


def _veth(one: Host, other: Host, prefix: int = 24) -> None:
    _ip('link', 'add', one.dev, 'type', 'veth', 'peer', 'name', other.dev)
    for host in (one, other):
        _ip('link', 'set', host.dev, 'netns', host.ns)
        _ip('-n', host.ns, 'addr', 'add', f'{host.ip}/{prefix}', 'dev', host.dev)
        _ip('-n', host.ns, 'link', 'set', host.dev, 'up')


@contextmanager
def veth_pair(tag: str = 'mlv'):
    """Yield ``(a, b)``: two :class:`Host` namespaces joined by a veth pair on one /24 LAN."""
    token, x, y = _new_names()
    a = Host(f'{tag}-{token}-a', f'{tag}{token}a', f'10.{x}.{y}.1')
    b = Host(f'{tag}-{token}-b', f'{tag}{token}b', f'10.{x}.{y}.2')
    with _namespaces([a.ns, b.ns], [a.dev]):
        _veth(a, b)
        yield a, b


@contextmanager
def routed_pair(tag: str = 'mlv'):
    """
    Yield ``(a, b)`` on two different /24s joined through a router namespace.

    Yield ``(a, b)`` on two different /24s joined through a router namespace (IPv4 forwarding
    on, no multicast routing): unicast passes between them, multicast does not — like two
    machines on different subnets.
    """
    token, x, y = _new_names()
    router = f'{tag}-{token}-r'
    a = Host(f'{tag}-{token}-a', f'{tag}{token}a', f'10.{x}.{y}.1')
    b = Host(f'{tag}-{token}-b', f'{tag}{token}b', f'10.{x}.{y + 1}.1')
    ra = Host(router, f'{tag}{token}ra', f'10.{x}.{y}.254')
    rb = Host(router, f'{tag}{token}rb', f'10.{x}.{y + 1}.254')
    with _namespaces([a.ns, b.ns, router], [a.dev, b.dev]):
        _veth(a, ra)
        _veth(b, rb)
        _ip('netns', 'exec', router, 'sysctl', '-q', '-w', 'net.ipv4.ip_forward=1')
        _ip('-n', a.ns, 'route', 'add', 'default', 'via', ra.ip)
        _ip('-n', b.ns, 'route', 'add', 'default', 'via', rb.ip)
        yield a, b
