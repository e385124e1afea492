"""Authentication and TLS on and off: what each configuration lets through, and what it costs.

    python -m benchmarks.service_auth [--clients 2] [--seconds 5] [--config configs/tiny.toml]

Four servers, one after another: plaintext without auth (--no-auth), plaintext with a bearer
token, TLS (a self-signed certificate made with openssl) without auth, TLS with a token. For
each: a client with the right token (where there is one) labels for --seconds (store off),
giving frames/s and latency percentiles; then the refusals are checked: no token and a wrong
token get UNAUTHENTICATED, a plaintext client of a TLS server fails (UNAVAILABLE), health
answers without a token; and the server's first log line says whether auth and TLS are on.
Starting without a token and without --no-auth must fail (exit 2).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import grpc

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import (
    REPO,
    TORCH_FREE_SERVE,
    percentiles,
    prepare_repository,
    sample_requests,
    serve,
)
from serving.health_check import wait_until_serving
from serving.testing import self_signed_certificate

TOKEN = "bench-token-0123456789"


def channel(target: str, cert: Path | None) -> grpc.Channel:
    options = [("grpc.max_send_message_length", 64 << 20)]
    if cert is None:
        return grpc.insecure_channel(target, options=options)
    credentials = grpc.ssl_channel_credentials(root_certificates=cert.read_bytes())
    return grpc.secure_channel(target.replace("[::]", "localhost").replace("127.0.0.1",
                               "localhost"), credentials, options=options)  # fmt: skip


def load(target: str, cert: Path | None, token: str | None, clients: int, seconds: float):
    from serving.client import pb2_grpc

    metadata = (("authorization", f"Bearer {token}"),) if token else ()
    latencies: list[float] = []
    failures: list[str] = []
    lock = threading.Lock()
    deadline = time.perf_counter() + seconds

    def client() -> None:
        requests = sample_requests(store=False)
        with channel(target, cert) as ch:
            stub = pb2_grpc.AutoLabelerStub(ch)
            i = 0
            while time.perf_counter() < deadline:
                start = time.perf_counter()
                try:
                    stub.LabelFrame(requests[i % 3], timeout=60, metadata=metadata)
                    with lock:
                        latencies.append(time.perf_counter() - start)
                except grpc.RpcError as error:
                    with lock:
                        failures.append(error.code().name)
                i += 1

    threads = [threading.Thread(target=client) for _ in range(clients)]
    began = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return {"frames_per_s": len(latencies) / (time.perf_counter() - began),
            "failed": failures, **percentiles(latencies)}  # fmt: skip


def refusals(target: str, cert: Path | None, token: str | None) -> dict[str, str]:
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    from serving.client import pb2, pb2_grpc

    found = {}
    for name, metadata in (("no token", ()), ("wrong token", (("authorization", "Bearer x"),))):
        with channel(target, cert) as ch:
            try:
                pb2_grpc.AutoLabelerStub(ch).GetModelInfo(pb2.GetModelInfoRequest(), timeout=10,
                                                          metadata=metadata)  # fmt: skip
                found[name] = "OK"
            except grpc.RpcError as error:
                found[name] = error.code().name
    with channel(target, cert) as ch:
        status = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=10)
        found["health without a token"] = health_pb2.HealthCheckResponse.ServingStatus.Name(
            status.status
        )
    if cert is not None:
        with grpc.insecure_channel(target) as ch:
            try:
                pb2_grpc.AutoLabelerStub(ch).GetModelInfo(pb2.GetModelInfoRequest(), timeout=5)
                found["plaintext client"] = "OK"
            except grpc.RpcError as error:
                found["plaintext client"] = error.code().name
    return found


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--clients", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--config", default="configs/tiny.toml")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="service_auth_"))
    repository = prepare_repository(work, args.config)
    cert, key = self_signed_certificate(work)
    env = {k: v for k, v in os.environ.items() if k != "DETMATCH_TOKEN"}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    refused = subprocess.run(
        [sys.executable, "-c", TORCH_FREE_SERVE, "--repository", str(repository), "--store",
         str(work / "store_refused"), "--port", "0"],
        env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    rows = []
    for tls in (False, True):
        for token in (None, TOKEN):
            args_tls = ("--tls-cert", str(cert), "--tls-key", str(key)) if tls else ()
            server_env = {"DETMATCH_TOKEN": token} if token else {}
            store = work / f"store_auth_{int(tls)}{int(bool(token))}_{time.time_ns()}"
            with serve(repository, store, *args_tls, env=server_env) as server:
                target = server.target
                if tls:
                    time.sleep(1.0)  # no plaintext health probe: let the model load
                    status = wait_until_serving(target, wait_s=120, poll_s=0.05,
                                                root_certificates=cert.read_bytes(),
                                                server_name="localhost")  # fmt: skip
                    if status != "SERVING":
                        raise TimeoutError(f"{target} is {status}, not SERVING, after 120 s")
                figures = load(target, cert if tls else None, token, args.clients, args.seconds)
                checks = refusals(target, cert if tls else None, token)
                starting = json.loads(server.log().splitlines()[0])
            rows.append({"tls": tls, "auth": bool(token), **figures, "checks": checks,
                         "logged": (starting["auth"], starting["tls"])})  # fmt: skip
    print(f"model {args.config}, {args.clients} clients, {args.seconds:.0f} s each, store off")
    print(f"\nstarting without a token or --no-auth: exit {refused.returncode}, "
          f"'{refused.stderr.strip().splitlines()[-1][:120]}'")  # fmt: skip
    print("\n| TLS | auth | frames/s | p50 ms | p99 ms | failed | no token | wrong token | "
          "plaintext client | health, no token | logged (auth, tls) |")  # fmt: skip
    print("| --- | --- | ---: | ---: | ---: | ---: | --- | --- | --- | --- | --- |")
    for row in rows:
        c = row["checks"]
        print(f"| {'on' if row['tls'] else 'off'} | {'token' if row['auth'] else 'off'} | "
              f"{row['frames_per_s']:.1f} | {row['p50_ms']:.0f} | {row['p99_ms']:.0f} | "
              f"{len(row['failed'])} | {c['no token']} | {c['wrong token']} | "
              f"{c.get('plaintext client', '-')} | {c['health without a token']} | "
              f"{row['logged']} |")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    argv = ["--clients", str(args.clients), "--seconds", str(args.seconds), "--config",
            args.config]  # fmt: skip
    print(f"\nrerun: {rerun('service_auth', argv)}")


if __name__ == "__main__":
    main()
