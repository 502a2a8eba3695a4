"""Batches on real Dask clusters: a stock scheduler and workers, a worker killed mid-scan, a client killed
mid-batch and rerun, a changed target, and an embedded cluster nobody else can reach.

Inversions here run at a budget of a few seconds: what is tested is where
scans go and what is written, not how good the phantoms are.
"""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from octcl._io import write_grey_png
from octcl.host.batch.report import read_summary_csv
from octcl.phantom import CONTRACT_Y_LIMIT_UM, Phantom
from octcl.render import render

DASK = str(Path(sys.executable).with_name("dask"))
#: Seconds per scan: a budget these scanner-rendered scans never need (each ends at its ceiling, in 6-7 s on two
#: slow cores), so that there is time for the first exact score beside another test's load too (12 s left it
#: out once with the suite in two workers).
BUDGET_S = 30


def wait_for(condition, timeout_s: float, what: str, process=None):
    deadline = time.monotonic() + timeout_s
    while not (result := condition()):
        if process is not None and process.poll() is not None:
            raise AssertionError(f"{what}: process ended first\n{process.stderr.read().decode()[-3000:]}")
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s} s"
        time.sleep(0.2)
    return result


@pytest.fixture(scope="module")
def skin_levels():
    """Three distinct synthetic targets' levels."""
    return [render(Phantom.skin(seed)).levels for seed in range(3)]


def make_targets(folder: Path, skin_levels, bad: bool = False) -> list[str]:
    """Targets in a nested tree, PNG and .npy; their names."""
    (folder / "Male/Cheek").mkdir(parents=True)
    (folder / "Female").mkdir()
    np.save(folder / "Male/Cheek/a.npy", skin_levels[0])
    write_grey_png(folder / "Female/b.png", skin_levels[1])
    names = ["Female/b.png", "Male/Cheek/a.npy"]
    if bad:
        np.save(folder / "Female/bad.npy", skin_levels[2].astype(np.float32))
        names.insert(0, "Female/bad.npy")
    return names


class StockCluster:
    """``dask scheduler`` and ``dask worker`` processes on 127.0.0.1, as a user starts them.

    ``--dashboard-address 127.0.0.1:0``: their HTTP servers (dashboard,
    health, metrics) otherwise listen on every interface, also with
    ``--no-dashboard`` (docs/batch.md).
    """

    def __init__(self, folder: Path):
        self.folder, self.workers = folder, {}
        self.file = folder / "scheduler.json"
        self.scheduler = subprocess.Popen(
            [DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", "--dashboard-address", "127.0.0.1:0",
             "--scheduler-file", str(self.file)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        wait_for(self.file.exists, 60, "scheduler file", self.scheduler)
        self.address = wait_for(lambda: json.loads(self.file.read_text() or "{}").get("address"), 10, "address")

    def start_worker(self, name: str) -> None:
        # No nanny: the process killed is the one running the scan.
        self.workers[name] = subprocess.Popen(
            [DASK, "worker", "--scheduler-file", str(self.file), "--nthreads", "1", "--no-nanny",
             "--host", "127.0.0.1", "--dashboard-address", "127.0.0.1:0", "--name", name,
             "--local-directory", str(self.folder / name)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def client(self):
        from distributed import Client

        return Client(self.address, timeout=30)

    def close(self) -> None:
        # Workers first: a worker whose scheduler is gone spends ~20 s trying to reach it before it exits.
        for group in (list(self.workers.values()), [self.scheduler]):
            for process in group:
                if process.poll() is None:
                    process.terminate()
            for process in group:
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()


@pytest.fixture(scope="module")
def stock_cluster(tmp_path_factory):
    cluster = StockCluster(tmp_path_factory.mktemp("cluster"))
    try:
        for name in ("w0", "w1"):
            cluster.start_worker(name)
        with cluster.client() as client:
            client.wait_for_workers(2, timeout=120)
        yield cluster
    finally:
        cluster.close()


def batch_command(targets: Path, out: Path, *options) -> list[str]:
    return [sys.executable, "-m", "octcl.cli", "invert", "--targets", str(targets), "--out", str(out),
            "--time-budget", str(BUDGET_S), "--quiet", "--json", *map(str, options)]


def check_outputs(out: Path, names: list[str], report_table) -> dict:
    """Every scan listed everywhere, every phantom whole and valid; returns summary.json."""
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(summary["scans"]) == sorted(names)
    csv_rows = read_summary_csv(out / "summary.csv")
    assert [row["scan"] for row in csv_rows] == list(summary["scans"])
    assert report_table((out / "report.html").read_text()) == [
        {column: row[column] or None for column in row} for row in csv_rows]
    for name, row in summary["scans"].items():
        if row["status"] in ("inverted", "resumed"):
            stem = out / Path(name).with_suffix("")
            phantom = Phantom.load(stem.with_suffix(".txt"), y_limit_um=CONTRACT_Y_LIMIT_UM)
            assert 0 < len(phantom) <= 300_000
            report = json.loads(stem.with_suffix(".report.json").read_text())
            assert report["target"] == name and report["batch"]["target"] == name
            # The summary's score is the report's; a budget with no time left for it leaves both out.
            assert row["mean"] == (None if report["components"] is None else report["components"]["mean"])
    return summary


def test_stock_cluster_survives_a_worker_killed_mid_scan(stock_cluster, skin_levels, tmp_path, report_table):
    """--scheduler: the scan of a SIGKILLed worker is redone on the other; a bad target fails alone."""
    names = make_targets(tmp_path / "targets", skin_levels, bad=True)
    out = tmp_path / "out"
    batch = subprocess.Popen(batch_command(tmp_path / "targets", out, "--scheduler", stock_cluster.address),
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    killed = None
    try:
        with stock_cluster.client() as client:
            def busy_worker():
                # A worker 3 s into a scan: past decoding, inside the inversion.
                processing = {address: keys for address, keys in client.processing().items()
                              if any(str(key).startswith("invert-") for key in keys)}
                now = time.monotonic()
                for address in processing:
                    busy_since.setdefault(address, now)
                return next((address for address in processing if now - busy_since[address] > 3), None)

            busy_since = {}
            address = wait_for(busy_worker, 240, "a worker inverting a scan", batch)
            killed = client.scheduler_info()["workers"][address]["name"]
            victim = stock_cluster.workers[killed]
            victim.send_signal(signal.SIGKILL)
            victim.wait(timeout=30)
            wait_for(lambda: address not in client.scheduler_info()["workers"], 30, "the scheduler noticing")
        stdout, stderr = batch.communicate(timeout=600)
    finally:
        if batch.poll() is None:
            batch.kill()
            batch.wait()
        if killed is not None:
            stock_cluster.start_worker(killed)  # for the next test
    assert batch.returncode == 0, stderr.decode()[-3000:]
    summary = check_outputs(out, names, report_table)
    assert json.loads(stdout) == summary
    statuses = {name: row["status"] for name, row in summary["scans"].items()}
    assert statuses == {"Female/bad.npy": "failed", "Female/b.png": "inverted", "Male/Cheek/a.npy": "inverted"}
    assert summary["scans"]["Female/bad.npy"]["error"].startswith("Female/bad.npy: float32 array")
    assert summary["counts"] == {"inverted": 2, "resumed": 0, "failed": 1, "pending": 0}
    assert "score" in summary and summary["cluster"].startswith(f"cluster at {stock_cluster.address}")


def test_killed_client_rerun_finishes_only_the_rest_and_redoes_a_changed_target(
        stock_cluster, skin_levels, tmp_path, report_table):
    names = make_targets(tmp_path / "targets", skin_levels)
    out = tmp_path / "out"
    command = batch_command(tmp_path / "targets", out, "--scheduler", stock_cluster.address)
    first = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        done = wait_for(lambda: sorted(out.rglob("*.report.json")), 300, "a first finished scan", first)
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    assert not (out / "summary.json").exists()  # killed before the end
    finished = {path.relative_to(out).as_posix(): path.with_suffix("").with_suffix(".txt").stat().st_mtime_ns
                for path in out.rglob("*.report.json")}
    assert 1 <= len(finished) < len(names), done

    rerun = subprocess.run(command, capture_output=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr.decode()[-3000:]
    summary = check_outputs(out, names, report_table)
    resumed = {name for name, row in summary["scans"].items() if row["status"] == "resumed"}
    assert {name.rsplit(".", 1)[0] for name in resumed} == {key.rsplit(".report", 1)[0] for key in finished}
    assert summary["counts"]["inverted"] == len(names) - len(finished)
    for report, mtime in finished.items():  # untouched by the rerun
        assert (out / report.replace(".report.json", ".txt")).stat().st_mtime_ns == mtime

    # A changed target is inverted again; the other is not.
    write_grey_png(tmp_path / "targets/Female/b.png", skin_levels[2])
    rerun = subprocess.run(command, capture_output=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr.decode()[-3000:]
    statuses = {name: row["status"] for name, row in check_outputs(out, names, report_table)["scans"].items()}
    assert statuses == {"Female/b.png": "inverted", "Male/Cheek/a.npy": "resumed"}


def test_ctrl_c_stops_cleanly_with_every_finished_phantom_valid(stock_cluster, skin_levels, tmp_path,
                                                                report_table):
    """SIGINT (Ctrl-C) after the first scan: exit 130, the summary lists the rest as pending."""
    names = make_targets(tmp_path / "targets", skin_levels)
    (tmp_path / "targets/Extra").mkdir()
    for index, levels in enumerate(skin_levels[:2]):  # more scans than workers: some are left when stopped
        np.save(tmp_path / f"targets/Extra/{index}.npy", levels)
        names.append(f"Extra/{index}.npy")
    out = tmp_path / "out"
    batch = subprocess.Popen(batch_command(tmp_path / "targets", out, "--scheduler", stock_cluster.address),
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        wait_for(lambda: sorted(out.rglob("*.report.json")), 300, "a first finished scan", batch)
        batch.send_signal(signal.SIGINT)
        status = batch.wait(timeout=60)
    finally:
        if batch.poll() is None:
            batch.kill()
            batch.wait()
    assert status == 130, batch.stderr.read().decode()[-3000:]
    statuses = {name: row["status"] for name, row in check_outputs(out, names, report_table)["scans"].items()}
    assert {"inverted", "pending"} == set(statuses.values()), statuses


def other_addresses() -> list[str]:
    """This machine's non-loopback IPv4 addresses."""
    import psutil

    return [address.address for addresses in psutil.net_if_addrs().values() for address in addresses
            if address.family == socket.AF_INET and not address.address.startswith("127.")]


def test_embedded_cluster_listens_on_loopback_only_and_workers_take_their_threads():
    import psutil

    from octcl.host.batch.runner import SCAN_RESOURCE, connect

    with connect(workers=1, threads_per_worker=2) as (client, description):
        assert "dashboard http://127.0.0.1:" in description
        processes = [psutil.Process(), *psutil.Process().children(recursive=True)]
        listening = [connection.laddr for process in processes
                     for connection in process.net_connections(kind="inet") if connection.status == "LISTEN"]
        ports = {address.port for address in listening}
        assert len(ports) >= 3  # scheduler, dashboard, worker (and its nanny)
        assert {address.ip for address in listening} == {"127.0.0.1"}
        for ip in other_addresses():
            for port in ports:
                with pytest.raises(OSError), socket.create_connection((ip, port), timeout=2):
                    pass

        def worker_settings(dask_worker):
            from octcl.host.threads import available_cores

            return (os.environ["OMP_NUM_THREADS"], os.environ["POCL_MAX_PTHREAD_COUNT"], available_cores(),
                    dict(dask_worker.state.total_resources))

        (settings,) = client.run(worker_settings).values()
        assert settings[:2] == ("2", "2") and settings[2] == min(2, len(psutil.Process().cpu_affinity()))
        assert settings[3] == {SCAN_RESOURCE: 1}


def test_unreachable_scheduler_is_a_one_line_error(tmp_path, skin_levels):
    make_targets(tmp_path / "targets", skin_levels)
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        port = unused.getsockname()[1]
    result = subprocess.run([*batch_command(tmp_path / "targets", tmp_path / "out"), "--scheduler",
                             f"tcp://127.0.0.1:{port}"], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "3s"})
    assert result.returncode == 2
    assert result.stderr.startswith(f"octcl invert: error: tcp://127.0.0.1:{port}: no Dask scheduler answers")


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make certificates")
def test_tls_cluster_takes_only_clients_with_a_certificate(tmp_path):
    """The recipe of docs/batch.md: a CA, one certificate, a TLS scheduler; plain clients are refused."""
    import dask
    from distributed import Security

    from octcl.host.batch.runner import connect

    def openssl(*arguments):
        subprocess.run(["openssl", *arguments], cwd=tmp_path, check=True, capture_output=True)

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=octcl-ca",
            "-keyout", "ca.key", "-out", "ca.pem")
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=octcl-cluster", "-keyout", "cluster.key",
            "-out", "cluster.csr")
    openssl("x509", "-req", "-in", "cluster.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-days", "2", "-out", "cluster.pem")
    tls = ["--tls-ca-file", "ca.pem", "--tls-cert", "cluster.pem", "--tls-key", "cluster.key"]
    scheduler = subprocess.Popen([DASK, "scheduler", "--protocol", "tls", "--host", "127.0.0.1", "--port", "0",
                                  "--dashboard-address", "127.0.0.1:0", "--scheduler-file", "scheduler.json", *tls],
                                 cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        file = tmp_path / "scheduler.json"
        address = wait_for(lambda: file.exists() and json.loads(file.read_text() or "{}").get("address"), 60,
                           "TLS scheduler", scheduler)
        assert address.startswith("tls://127.0.0.1:")
        security = Security(tls_ca_file=str(tmp_path / "ca.pem"), tls_client_cert=str(tmp_path / "cluster.pem"),
                            tls_client_key=str(tmp_path / "cluster.key"), require_encryption=True)
        with connect(address, security=security) as (client, description):
            assert description.startswith(f"cluster at {address}: 0 workers")
            assert client.scheduler_info()["address"] == address
        with dask.config.set({"distributed.comm.timeouts.connect": "5s"}), \
                pytest.raises(ConnectionError, match="no Dask scheduler answers"):
            with connect(address.replace("tls://", "tcp://")):
                pass
    finally:
        scheduler.terminate()
        scheduler.wait(timeout=20)


def test_target_larger_than_any_scan_fails_unread(tmp_path):
    """A target file larger than MAX_IMAGE_FILE_BYTES is a failed scan, named, without being read into memory
    (and with nothing left to invert, no cluster is started)."""
    from octcl._io import MAX_IMAGE_FILE_BYTES
    from octcl.host.batch import invert_batch

    (tmp_path / "targets").mkdir()
    with open(tmp_path / "targets" / "huge.npy", "wb") as handle:  # sparse: no disk used
        handle.truncate(MAX_IMAGE_FILE_BYTES + 1)
    summary = invert_batch(tmp_path / "targets", tmp_path / "out", time_budget_s=BUDGET_S, workers=1)
    row = summary["scans"]["huge.npy"]
    assert summary["counts"]["failed"] == 1 and row["status"] == "failed" and summary["cluster"] is None
    assert row["error"] == (f"{tmp_path / 'targets' / 'huge.npy'}: {MAX_IMAGE_FILE_BYTES + 1:,} bytes, more than "
                            f"the {MAX_IMAGE_FILE_BYTES:,} an image octcl reads may have")
