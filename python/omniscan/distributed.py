"""Twins of many captures on a Ray cluster (docs/scale-out.md).

    python -m omniscan.distributed twin CAPTURE... --out OUT [--address HOST:PORT]
        [--gpus-per-task 1] [--cpus-per-task N] [--steps N --downscale N --backend B] [--json]

CAPTURE and OUT are local paths (on a filesystem every node shares) or
``s3://bucket/prefix`` URIs on any S3-compatible store (boto3; the endpoint
from ``AWS_ENDPOINT_URL``). Each capture is one Ray task; ``OUT/<capture
name>/`` gets the twin's files and ``report.json`` (the twin's report).

Crash safety and idempotence:

- A task works in ``OUT/.work/<name>/`` (on S3: a local folder synced to
  that prefix every ``OMNISCAN_SYNC_SECONDS``, 30 by default). The twin
  resumes from what is there (its finished stages and training
  checkpoints), so a retried task goes on where the killed one stopped.
- Committing is atomic and the first commit wins: on a filesystem the work
  folder is renamed to ``OUT/<name>``; on S3 the files are uploaded and then
  ``report.json`` is put only if absent (a conditional put), the object's
  commit mark. A task or driver that finds ``OUT/<name>/report.json`` skips
  the object, so a resubmitted job does only what is left.
- Each task runs the ``omniscan`` command in a subprocess: a crash or a
  stuck GPU takes down that process only, each run starts with a clean
  device, and its exit status says what to do: 0 committed; 1 (the capture
  or settings are bad) is reported and not retried; 74 and 75 (a file
  error, an output in use), a signal, or the worker's death are retried by
  Ray, up to ``--max-retries``.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional

RETRIED_EXIT_CODES = {74, 75}


class Retry(Exception):
    """A failure another attempt may not have (Ray retries the task)."""


@dataclass
class ObjectResult:
    """What became of one capture."""

    name: str
    capture: str
    status: str  # committed, already-committed, skipped, failed
    attempts: int = 0
    seconds: float = 0.0
    psnr: Optional[float] = None
    error: Optional[str] = None


# ---------------------------------------------------------------- storage


def is_s3(uri: str) -> bool:
    return uri.startswith("s3://")


def split_s3(uri: str):
    bucket, _, prefix = uri[len("s3://") :].partition("/")
    return bucket, prefix.strip("/")


def name_of(capture: str) -> str:
    return capture.rstrip("/").rsplit("/", 1)[-1]


def _skipped(path: pathlib.Path) -> bool:
    """Files a work folder holds that are not outputs: locks, temporaries."""
    return path.name.endswith(".lock") or path.name.startswith(".omniscan-tmp-")


class LocalStore:
    """Outputs on a filesystem every node sees."""

    def __init__(self, root: str) -> None:
        self.root = pathlib.Path(root)

    def committed(self, name: str) -> bool:
        return (self.root / name / "report.json").exists()

    def work(self, name: str) -> pathlib.Path:
        path = self.root / ".work" / name
        path.mkdir(parents=True, exist_ok=True)
        return path

    def push(self, name: str, local: pathlib.Path) -> None:
        """The work folder is already where every node sees it."""

    def attempt(self, name: str) -> int:
        """Counts this attempt; returns its number (1 for the first)."""
        counter = self.root / ".work" / f"{name}.attempts"
        counter.parent.mkdir(parents=True, exist_ok=True)
        n = int(counter.read_text()) + 1 if counter.exists() else 1
        counter.write_text(str(n))
        return n

    def attempts(self, name: str) -> int:
        counter = self.root / ".work" / f"{name}.attempts"
        return int(counter.read_text()) if counter.exists() else 0

    def commit(self, name: str, local: pathlib.Path, report: dict) -> bool:
        (local / "report.json").write_text(json.dumps(report, indent=2))
        for lock in local.glob("*.lock"):
            lock.unlink()
        try:
            os.rename(local, self.root / name)  # atomic; fails if the target exists
        except OSError:
            if self.committed(name):
                shutil.rmtree(local, ignore_errors=True)
                return False
            raise
        return True


class S3Store:
    """Outputs on an S3-compatible store."""

    def __init__(self, uri: str) -> None:
        import boto3  # the `distributed` extra

        self.bucket, self.prefix = split_s3(uri)
        self.s3 = boto3.client("s3")
        self.pushed: Dict[str, tuple] = {}

    def key(self, *parts: str) -> str:
        return "/".join(p for p in (self.prefix, *parts) if p)

    def committed(self, name: str) -> bool:
        from botocore.exceptions import ClientError

        try:
            self.s3.head_object(Bucket=self.bucket, Key=self.key(name, "report.json"))
            return True
        except ClientError:
            return False

    def _keys(self, prefix: str):
        pages = self.s3.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix)
        for page in pages:
            for item in page.get("Contents", []):
                yield item["Key"]

    def work(self, name: str) -> pathlib.Path:
        """A local folder holding what earlier attempts pushed."""
        local = pathlib.Path(tempfile.mkdtemp(prefix=f"omniscan-{name}-"))
        prefix = self.key(".work", name) + "/"
        for key in self._keys(prefix):
            target = local / key[len(prefix) :]
            target.parent.mkdir(parents=True, exist_ok=True)
            self.s3.download_file(self.bucket, key, str(target))
            stat = target.stat()
            self.pushed[str(target)] = (stat.st_size, stat.st_mtime_ns)
        return local

    def push(self, name: str, local: pathlib.Path) -> None:
        """Uploads the work folder's files changed since the last push."""
        for path in sorted(local.rglob("*")):
            if not path.is_file() or _skipped(path):
                continue
            try:
                stat = path.stat()
            except FileNotFoundError:  # replaced meanwhile; the next push takes it
                continue
            stamp = (stat.st_size, stat.st_mtime_ns)
            if self.pushed.get(str(path)) == stamp:
                continue
            rel = path.relative_to(local).as_posix()
            try:
                self.s3.upload_file(str(path), self.bucket, self.key(".work", name, rel))
            except FileNotFoundError:
                continue
            self.pushed[str(path)] = stamp

    def _count(self, name: str) -> int:
        from botocore.exceptions import ClientError

        try:
            body = self.s3.get_object(Bucket=self.bucket, Key=self.key(".work", f"{name}.attempts"))["Body"]
            return int(body.read())
        except ClientError:
            return 0

    def attempt(self, name: str) -> int:
        n = self._count(name) + 1
        self.s3.put_object(Bucket=self.bucket, Key=self.key(".work", f"{name}.attempts"), Body=str(n).encode())
        return n

    def attempts(self, name: str) -> int:
        return self._count(name)

    def commit(self, name: str, local: pathlib.Path, report: dict) -> bool:
        from botocore.exceptions import ClientError

        # The files first (identical bytes whoever uploads them: the twin
        # is deterministic), then the commit mark, only if absent.
        for path in sorted(local.rglob("*")):
            if path.is_file() and not _skipped(path):
                rel = path.relative_to(local).as_posix()
                self.s3.upload_file(str(path), self.bucket, self.key(name, rel))
        try:
            self.s3.put_object(
                Bucket=self.bucket,
                Key=self.key(name, "report.json"),
                Body=json.dumps(report, indent=2).encode(),
                IfNoneMatch="*",
            )
        except ClientError as e:
            if e.response.get("Error", {}).get("Code") in ("PreconditionFailed", "412", "ConditionalRequestConflict"):
                return False
            raise
        finally:
            shutil.rmtree(local, ignore_errors=True)
        for key in list(self._keys(self.key(".work", name) + "/")):
            self.s3.delete_object(Bucket=self.bucket, Key=key)
        return True

    def download_capture(self, uri: str) -> pathlib.Path:
        bucket, prefix = split_s3(uri)
        local = pathlib.Path(tempfile.mkdtemp(prefix="omniscan-capture-")) / name_of(uri)
        for page in self.s3.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix + "/"):
            for item in page.get("Contents", []):
                target = local / item["Key"][len(prefix) + 1 :]
                target.parent.mkdir(parents=True, exist_ok=True)
                self.s3.download_file(bucket, item["Key"], str(target))
        if not (local / "capture.json").exists():
            raise FileNotFoundError(f"{uri}: no capture.json under it")
        return local


def store_for(uri: str):
    return S3Store(uri) if is_s3(uri) else LocalStore(uri)


# ---------------------------------------------------------------- one task


def omniscan_command() -> List[str]:
    """The command a task runs: ``OMNISCAN_BIN`` if set, else this
    package's own ``omniscan`` (the same command line, in a new process)."""
    binary = os.environ.get("OMNISCAN_BIN")
    return [binary] if binary else [sys.executable, "-m", "omniscan"]


def _die_with_parent() -> None:
    """The omniscan process ends when the Ray worker that started it does
    (Linux's PR_SET_PDEATHSIG), so a killed worker leaves no run behind."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)
    except OSError:
        pass


def gpu_flags() -> List[str]:
    """The GPU Ray assigned this task, as the command line's ``--gpu``: by
    PCI bus id where nvidia-smi can name it (wgpu's adapter order need not
    be CUDA's), else by index."""
    try:
        import ray

        ids = ray.get_gpu_ids()
    except Exception:
        return []
    if not ids:
        return []
    gpu = str(ids[0])
    try:
        query = subprocess.run(
            ["nvidia-smi", "--query-gpu=pci.bus_id", "--format=csv,noheader", "-i", gpu],
            capture_output=True,
            text=True,
            timeout=10,
        )
        if query.returncode == 0 and query.stdout.strip():
            return ["--gpu", query.stdout.strip().splitlines()[0]]
    except (OSError, subprocess.TimeoutExpired):
        pass
    return ["--gpu", gpu]


def _error_of(stderr: str) -> str:
    """The command line's error (from its last `error:` line on), in one line."""
    lines = stderr.strip().splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith("error:")]
    tail = lines[starts[-1] :] if starts else lines[-1:]
    return " ".join(line.strip() for line in tail)[:1000]


def twin_one(capture: str, out: str, settings: Dict[str, str]) -> dict:
    """Makes and commits one capture's twin; the body of a Ray task."""
    store = store_for(out)
    name = name_of(capture)
    started = time.monotonic()
    attempt = store.attempt(name)
    result = ObjectResult(name=name, capture=capture, status="committed", attempts=attempt)
    if store.committed(name):
        result.status = "already-committed"
        return asdict(result)
    local_capture = store.download_capture(capture) if is_s3(capture) else pathlib.Path(capture)
    work = store.work(name)
    command = [*omniscan_command(), "twin", str(local_capture), "--out", str(work), "--json"]
    for key, value in settings.items():
        command += [f"--{key.replace('_', '-')}", str(value)]
    command += gpu_flags()
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_die_with_parent
    )
    stop = threading.Event()
    interval = float(os.environ.get("OMNISCAN_SYNC_SECONDS", "30"))

    def sync() -> None:
        while not stop.wait(interval):
            store.push(name, work)

    syncer = threading.Thread(target=sync, daemon=True)
    syncer.start()
    stdout, stderr = process.communicate()
    stop.set()
    syncer.join()
    if process.returncode != 0:
        store.push(name, work)  # what the next attempt resumes from
        message = _error_of(stderr) or f"exit {process.returncode}"
        if process.returncode == 1:
            result.status, result.error = "failed", message
            result.seconds = time.monotonic() - started
            return asdict(result)
        raise Retry(f"{name}: omniscan exited {process.returncode}: {message}")
    report = json.loads(stdout)
    if not store.commit(name, work, report):
        result.status = "already-committed"
    result.seconds = time.monotonic() - started
    test = report.get("stages", {}).get("twin", {}).get("report", {}).get("test", {})
    result.psnr = test.get("psnr")
    return asdict(result)


# ---------------------------------------------------------------- the driver


def run(
    captures: List[str],
    out: str,
    settings: Dict[str, str],
    address: Optional[str] = None,
    gpus_per_task: float = 0,
    cpus_per_task: float = 1,
    max_retries: int = 3,
) -> List[ObjectResult]:
    """Twins every capture on the cluster at ``address`` (a local one when
    None); returns what became of each, in the captures' order."""
    import ray

    store = store_for(out)
    results: Dict[str, ObjectResult] = {}
    pending = {}
    names = [name_of(c) for c in captures]
    if len(set(names)) != len(names):
        raise ValueError(f"captures must have distinct folder names: {names}")
    ray.init(address=address, ignore_reinit_error=True, logging_level="ERROR", log_to_driver=False)
    task = ray.remote(twin_one).options(
        num_cpus=cpus_per_task,
        num_gpus=gpus_per_task,
        max_retries=max_retries,
        retry_exceptions=[Retry],
    )
    for capture, name in zip(captures, names):
        if store.committed(name):
            results[name] = ObjectResult(name, capture, "skipped", store.attempts(name))
        else:
            pending[task.remote(capture, out, settings)] = (capture, name)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        capture, name = pending.pop(done[0])
        try:
            results[name] = ObjectResult(**ray.get(done[0]))
        except Exception as e:  # retries exhausted, or a task that cannot run
            cause = getattr(e, "cause", None) or e
            results[name] = ObjectResult(name, capture, "failed", store.attempts(name), error=str(cause).strip().splitlines()[-1])
    return [results[n] for n in names]


def _summary(results: List[ObjectResult]) -> str:
    lines = [f"{'object':24} {'status':18} {'attempts':>8} {'seconds':>8} {'PSNR dB':>8}"]
    for r in results:
        psnr = f"{r.psnr:.2f}" if r.psnr is not None else "-"
        lines.append(f"{r.name:24} {r.status:18} {r.attempts:>8} {r.seconds:>8.1f} {psnr:>8}")
        if r.error:
            lines.append(f"    {r.error}")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m omniscan.distributed", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    twin = commands.add_parser("twin", help="twin every capture, one Ray task each")
    twin.add_argument("captures", nargs="+", help="capture folders or s3:// prefixes")
    twin.add_argument("--out", required=True, help="output folder or s3:// prefix")
    twin.add_argument("--address", help="the Ray cluster (HOST:PORT or auto); a local one when not given")
    twin.add_argument("--gpus-per-task", type=float, default=0, help="GPUs each task takes (default 0: CPU)")
    twin.add_argument("--cpus-per-task", type=float, default=1, help="CPU cores each task takes")
    twin.add_argument("--max-retries", type=int, default=3, help="retries of a task whose worker died or failed transiently")
    twin.add_argument("--steps", type=int, help="training steps per model (omniscan twin --steps)")
    twin.add_argument("--downscale", type=int, help="image downscale (omniscan twin --downscale)")
    twin.add_argument("--backend", choices=["auto", "cpu", "gpu"], help="omniscan twin --backend")
    twin.add_argument("--json", action="store_true", help="print the summary as JSON")
    args = parser.parse_args(argv)
    settings = {k: v for k, v in (("steps", args.steps), ("downscale", args.downscale), ("backend", args.backend)) if v is not None}
    # Ray prints its own notices (a worker that died, a retry) on stdout;
    # they go to stderr, and stdout carries the summary alone.
    sys.stdout.flush()
    stdout = os.dup(1)
    os.dup2(2, 1)
    try:
        results = run(
            args.captures,
            args.out,
            settings,
            address=args.address,
            gpus_per_task=args.gpus_per_task,
            cpus_per_task=args.cpus_per_task,
            max_retries=args.max_retries,
        )
    finally:
        sys.stdout.flush()
        os.dup2(stdout, 1)
        os.close(stdout)
    if args.json:
        print(json.dumps([asdict(r) for r in results], indent=2))
    else:
        print(_summary(results))
    return 1 if any(r.status == "failed" for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
