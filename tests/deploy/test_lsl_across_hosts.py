"""LSL across hosts, as docker-compose.yml wires it (conftest.ComposeLab): a real LSL EEG
stream and marker stream published on the lab's acquisition PC ("headset-pc", a network
namespace on another network, behind a router, with a plain liblsl configuration), and
compose's EEG service in its own namespace on the compose network, configured as
docs/deploy.md tells a lab: ``BGRL_LSL_CONFIG`` in .env names an LSL file whose
``KnownPeers`` lists the acquisition PC, mounted at ``/etc/lsl_api/lsl_api.cfg`` and named
by ``LSLAPICFG``. The EEG service resolves both streams by unicast through that peer,
records them and stores the recording. A router forwards no multicast or broadcast (as
Docker's bridge network carries none between the LAN and a container), so with the
repository's default file (no known peer) nothing is found: the test checks that too."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from tests.deploy.conftest import DOT_ENV, ComposeLab
from tests.deploy.netns import SUBNET, Lab, ip, netns_unavailable
from tests.deploy.roles import ROOT
from tests.helpers import env_without_bgrl

pytestmark = pytest.mark.netns
EEG_STREAM = "netns-headset-EEG"
MARKER_STREAM = "netns-headset-Markers"
RECORD_S = 7.0
"""Seconds recorded (a stored recording needs 5 s and at least one action)."""

HEADSET = """
import itertools, sys, time
from services.core.markers import ActionMarker
from services.eeg.live import lsl
from services.eeg.virtual.subject import simulate_recording
from services.sim.lsl_markers import MarkerPublisher
raw = simulate_recording([True, False] * 5, quality=1.0, seed=3, sfreq=256.0)
player = lsl.replay(raw, name=sys.argv[1], chunk_size=32, n_repeat=100, source_id="netns-eeg")
markers = MarkerPublisher("netns-headset", name=sys.argv[2])
print("publishing", flush=True)
for step in itertools.count():  # one action every 0.5 s, alternately correct and wrong
    time.sleep(0.5)
    markers.publish(ActionMarker(session_id="netns", step=step, episode=0, action=step % 3,
                                 correct=step % 2 == 0, timestamp=lsl.lsl_clock()))
"""

RESOLVE = """
import sys
from mne_lsl.lsl import resolve_streams
print(len(resolve_streams(timeout=2.0, name=sys.argv[1])))
"""


LAN = "10.231.78"
"""The lab LAN of the acquisition PC (the compose network is netns.SUBNET)."""


def add_routed_host(lab: Lab, host: str, router: str) -> None:
    """``host`` on a network of its own behind ``router`` (a host on the switch that
    forwards IP between the two, not multicast), reachable by name from every host."""
    gateway = lab.add_host(router)
    ns, ns_router = lab.namespace(host), lab.namespace(router)
    ip("netns", "add", ns)
    lab.hosts[host], lab.aliases[host] = f"{LAN}.2", [host]  # lab.close() removes it
    ip("link", "add", "lan0", "netns", ns_router, "type", "veth", "peer", "name", "eth0",
       "netns", ns)  # fmt: skip
    ip("addr", "add", f"{LAN}.1/24", "dev", "lan0", netns=ns_router)
    ip("link", "set", "lan0", "up", netns=ns_router)
    ip("link", "set", "lo", "up", netns=ns)
    ip("addr", "add", f"{LAN}.2/24", "dev", "eth0", netns=ns)
    ip("link", "set", "eth0", "up", netns=ns)
    ip("route", "add", "default", "via", f"{LAN}.1", netns=ns)
    forward = lab.run(router, ["sysctl", "-qw", "net.ipv4.ip_forward=1"])
    assert forward.returncode == 0, forward.stderr
    for other in lab.hosts:
        if other not in (host, router):
            ip("route", "add", f"{LAN}.0/24", "via", gateway, netns=lab.namespace(other))
    lab.write_hosts_files()
    assert gateway.startswith(SUBNET)


def plain_liblsl_env() -> dict[str, str]:
    """A lab machine's environment: no liblsl configuration file named (this test run's own
    loopback one, tests/conftest.py, is left out)."""
    return {k: v for k, v in env_without_bgrl().items() if k != "LSLAPICFG"}


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ComposeLab]:
    reason = netns_unavailable()
    if reason is not None:
        pytest.skip(f"the namespace deployment {reason}")
    root = tmp_path_factory.mktemp("lsl-hosts")
    config = root / "lsl_api.cfg"  # the lab's copy of deploy/lsl_api.cfg, its peer listed
    config.write_text(
        (ROOT / "deploy" / "lsl_api.cfg")
        .read_text()
        .replace("KnownPeers = {}", "KnownPeers = {headset-pc}")
    )
    compose = None
    try:
        compose = ComposeLab(root, {"BGRL_LSL_CONFIG": str(config)})
        add_routed_host(compose.lab, "headset-pc", "lan-router")
        yield compose
    finally:
        if compose is not None:
            compose.close()


def test_the_eeg_service_records_a_headsets_lsl_stream_from_another_host(lab: ComposeLab):
    assert "KnownPeers = {}" in (ROOT / "deploy" / "lsl_api.cfg").read_text()
    lab.start("eeg")  # compose's command and environment, LSLAPICFG included
    headset = lab.lab.start(
        "headset-pc", [sys.executable, "-c", HEADSET, EEG_STREAM, MARKER_STREAM],
        env=plain_liblsl_env(), log=lab.log("headset-pc"), cwd=lab.root,
    )  # fmt: skip
    lab.procs["headset-pc"] = headset
    lab.wait_until("headset-pc", lambda: "publishing" in lab.tail("headset-pc"), 60)

    # the repository's default file lists no peer: from the EEG host nothing is found
    default = {**plain_liblsl_env(), "LSLAPICFG": str(ROOT / "deploy" / "lsl_api.cfg")}
    found = lab.lab.run("eeg", [sys.executable, "-c", RESOLVE, EEG_STREAM], default, 60)
    assert found.returncode == 0, found.stderr[-2000:]
    assert found.stdout.split()[-1] == "0", found.stdout

    lab.wait_healthy("eeg")
    url = f"http://{lab.lab.hosts['eeg']}:8002"
    headers = {"X-Service-Token": DOT_ENV["BGRL_SERVICE_TOKEN"]}

    def call(method: str, path: str, **kwargs: Any) -> httpx.Response:
        return httpx.request(method, url + path, headers=headers, timeout=30, **kwargs)

    with lab.lab.inside("lab-pc") as run:  # the api's and workers' view: over the network
        body = {"stream_name": EEG_STREAM, "marker_stream": MARKER_STREAM}
        connected = run(lambda: call("POST", "/live", json=body))
        assert connected.status_code == 200, connected.text
        assert connected.json()["source"] == "lsl"
        started = run(lambda: call("POST", "/live/recording", json={"name": "netns-lsl"}))
        assert started.status_code == 201, started.text
        time.sleep(RECORD_S)
        status = run(lambda: call("GET", "/live")).json()
        stored = run(lambda: call("DELETE", "/live/recording"))
        run(lambda: call("DELETE", "/live"))
    assert stored.status_code == 200, stored.text
    recording = stored.json()
    assert status["connected"] and status["recording"]["n_markers"] >= RECORD_S / 0.5 - 4
    assert recording["format"] == "bdf"
    assert recording["duration_s"] >= RECORD_S - 2 and recording["sfreq"] == 256.0
    assert recording["n_actions"] >= 4 and 0 < recording["n_errors"] < recording["n_actions"]
    assert (lab.volume("eegdata", "eeg") / "recordings" / f"{recording['id']}.bdf").is_file()
