"""deploy/ and docker/ as written: every KubeRay object validates against KubeRay's own schema
(deploy/schemas, from the operator's CRDs, deploy/schemas/SOURCE.json), strictly (an unknown field
is an error, as with `kubectl apply --validate=strict`), and the manifest agrees with what the run
asks for."""

import copy
import gzip
import json
import shlex
from pathlib import Path

import jsonschema
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCHEMAS = ROOT / "deploy" / "schemas"


def _strict(schema):
    """Kubernetes prunes or (strict validation) rejects fields a structural schema does not
    declare; JSON Schema allows them unless told: say so on every object with properties, except
    where the CRD keeps unknown fields."""
    schema = copy.deepcopy(schema)

    def walk(node):
        if isinstance(node, dict):
            if node.get("properties") and not node.get("x-kubernetes-preserve-unknown-fields"):
                node.setdefault("additionalProperties", False)
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(schema)
    return schema


def _validator(kind):
    schema = json.loads(gzip.decompress((SCHEMAS / f"{kind.lower()}-v1.schema.json.gz").read_bytes()))
    return jsonschema.Draft7Validator(_strict(schema))


def _documents():
    return [d for d in yaml.safe_load_all((ROOT / "deploy" / "rayjob.yaml").read_text()) if d]


def test_the_schemas_name_their_source():
    source = json.loads((SCHEMAS / "SOURCE.json").read_text())
    assert source["repository"] == "https://github.com/ray-project/kuberay" and source["tag"] == "v1.7.0"
    assert len(source["commit"]) == 40 and set(source["files"]) == {p.name for p in SCHEMAS.glob("*.schema.json.gz")}


def test_every_kuberay_object_validates_strictly():
    docs = _documents()
    kinds = [d["kind"] for d in docs]
    assert kinds.count("RayJob") == 1 and "Service" in kinds
    for doc in docs:
        if doc["apiVersion"] != "ray.io/v1":
            assert (doc["apiVersion"], doc["kind"]) in {("v1", "Service"), ("networking.k8s.io/v1", "NetworkPolicy")}
            continue
        errors = sorted(_validator(doc["kind"]).iter_errors(doc), key=lambda e: list(e.path))
        assert not errors, [f"{'/'.join(map(str, e.path))}: {e.message}" for e in errors[:5]]
    job = next(d for d in docs if d["kind"] == "RayJob")
    cluster = {"apiVersion": "ray.io/v1", "kind": "RayCluster", "metadata": {"name": "c"}, "spec": job["spec"]["rayClusterSpec"]}
    assert not list(_validator("RayCluster").iter_errors(cluster))


def test_the_strict_schema_catches_a_misspelt_field_and_a_wrong_type():
    job = next(d for d in _documents() if d["kind"] == "RayJob")
    bad = copy.deepcopy(job)
    bad["spec"]["shutdownAfterJobFinish"] = True  # the field is shutdownAfterJobFinishes
    assert any("shutdownAfterJobFinish" in e.message for e in _validator("RayJob").iter_errors(bad))
    bad = copy.deepcopy(job)
    bad["spec"]["rayClusterSpec"]["workerGroupSpecs"][0]["replicas"] = "four"
    assert list(_validator("RayJob").iter_errors(bad))


def test_the_manifest_gives_what_the_run_needs():
    """The entrypoint's config fits the cluster the manifest makes (the check the driver runs),
    keeps its state on a storage URI every node reaches with the same credentials (no shared
    volume), works in the head's scratch volume by an absolute path, continues a retried job, and
    reaches its HTTP service through the Service only with a token; the stop grace covers a checkpoint."""
    from covers_dist.config import load_config
    from covers_dist.runtime.placement import check_fits

    docs = _documents()
    job = next(d for d in docs if d["kind"] == "RayJob")
    argv = shlex.split(job["spec"]["entrypoint"])
    assert argv[:2] == ["covers-dist", "train"] and "--resume-existing" in argv
    run_dir = argv[argv.index("--run-dir") + 1]
    sets = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
    cfg = load_config(argv[argv.index("--config") + 1], [*sets, f"runtime.run_dir={run_dir}"])
    assert Path(run_dir).is_absolute() and cfg.api.enabled and cfg.api.host == "0.0.0.0"
    assert cfg.runtime.storage and cfg.runtime.storage.startswith("s3://")

    spec = job["spec"]["rayClusterSpec"]
    head = spec["headGroupSpec"]
    nodes = [{"CPU": float(head["rayStartParams"]["num-cpus"])}]
    for group in spec["workerGroupSpecs"]:
        (container,) = group["template"]["spec"]["containers"]
        limits = container["resources"]["limits"]
        node = {"CPU": float(limits["cpu"]), "GPU": float(limits.get("nvidia.com/gpu", 0))}
        nodes += [node] * group["minReplicas"]  # what exists when the driver checks
    check_fits(cfg, nodes)

    (head_container,) = head["template"]["spec"]["containers"]
    env = {e["name"]: e for e in head_container["env"]}
    assert "secretKeyRef" in env["COVERS_API_TOKEN"]["valueFrom"]
    wait = int(env["RAY_JOB_STOP_WAIT_TIME_S"]["value"])
    assert 60 <= wait < head["template"]["spec"]["terminationGracePeriodSeconds"]
    mounts = {m["mountPath"] for m in head_container["volumeMounts"]}
    assert any(run_dir.startswith(m + "/") for m in mounts)
    service = next(d for d in docs if d["kind"] == "Service")
    assert service["spec"]["selector"]["ray.io/originated-from-cr-name"] == job["metadata"]["name"]
    assert service["spec"]["ports"][0]["targetPort"] == cfg.api.port
    pods = [head["template"]["spec"], *(g["template"]["spec"] for g in spec["workerGroupSpecs"])]
    for pod in pods:
        (container,) = pod["containers"]
        assert {"secretRef": {"name": "covers-s3"}} in container.get("envFrom", []), container["name"]
        assert not any("persistentVolumeClaim" in v for v in pod.get("volumes", []))


def _env_names(container):
    return {e["name"] for e in container.get("env", [])} | {
        f"secret:{ref['secretRef']['name']}" for ref in container.get("envFrom", []) if "secretRef" in ref
    }


def test_only_the_runs_own_pods_can_drive_the_cluster():
    """Ray's token authentication is on from a Secret (every Ray container by authOptions, the
    submitter by its own env), the dashboard binds beyond the pod only with it, a NetworkPolicy
    admits only the run's pods (and the API's clients on the API port), and each secret reaches
    only the pods that use it: the storage's the Ray nodes, the API token the head."""
    docs = _documents()
    job = next(d for d in docs if d["kind"] == "RayJob")
    spec = job["spec"]["rayClusterSpec"]
    assert spec["authOptions"] == {"mode": "token", "secretName": "covers-ray"}
    head = spec["headGroupSpec"]
    if head["rayStartParams"].get("dashboard-host", "127.0.0.1") not in ("127.0.0.1", "localhost"):
        assert spec["authOptions"]["mode"] == "token"

    submitter = job["spec"]["submitterPodTemplate"]
    (sub,) = submitter["spec"]["containers"]
    env = {e["name"]: e for e in sub["env"]}
    assert env["RAY_AUTH_MODE"]["value"] == "token"
    assert env["RAY_AUTH_TOKEN"]["valueFrom"]["secretKeyRef"] == {"name": "covers-ray", "key": "auth_token"}
    assert _env_names(sub) == {"RAY_AUTH_MODE", "RAY_AUTH_TOKEN"}  # no storage credentials, no API token

    label = {"covers-dist/run": job["metadata"]["name"]}
    templates = [head["template"], *(g["template"] for g in spec["workerGroupSpecs"]), submitter]
    for template in templates:
        assert template["metadata"]["labels"].items() >= label.items()
    (head_container,) = head["template"]["spec"]["containers"]
    assert {"COVERS_API_TOKEN", "secret:covers-s3"} <= _env_names(head_container)
    for group in spec["workerGroupSpecs"]:
        (container,) = group["template"]["spec"]["containers"]
        assert "secret:covers-s3" in _env_names(container) and "COVERS_API_TOKEN" not in _env_names(container)

    (policy,) = [d for d in docs if d["kind"] == "NetworkPolicy"]
    assert policy["spec"]["podSelector"]["matchLabels"] == label and policy["spec"]["policyTypes"] == ["Ingress"]
    rules = policy["spec"]["ingress"]
    assert all(len(rule["from"]) == 1 and set(rule["from"][0]) == {"podSelector"} for rule in rules)  # no ipBlock
    own = [r for r in rules if r["from"][0]["podSelector"]["matchLabels"] == label]
    assert len(own) == 1 and "ports" not in own[0]
    clients = [r for r in rules if r not in own]
    service = next(d for d in docs if d["kind"] == "Service")
    api_port = service["spec"]["ports"][0]["targetPort"]
    assert clients and all(r["ports"] == [{"protocol": "TCP", "port": api_port}] for r in clients)


def test_the_dockerfile_follows_the_ray_image_conventions():
    """A non-root user (uid 1000, as rayproject/ray), bash and wget for KubeRay's probes, a CPU and a
    CUDA build of torch, the package installed as a package at the lock's versions (not editable,
    no test tools), and the image the manifest names for the GPU nodes is the CUDA one. (No Docker
    engine here: the file is checked, not built.)"""
    text = (ROOT / "docker" / "Dockerfile").read_text()
    lines = [line.strip() for line in text.splitlines() if not line.strip().startswith("#")]
    assert "USER ray" in lines and any("useradd" in line and "--uid 1000" in line for line in lines)
    assert "wget" in text and "bash" in text and "ARG TORCH=cpu" in lines
    assert "cpu)" in text and "cuda)" in text and "TORCH_CPU_INDEX" in text
    body = "\n".join(lines)
    assert "-c /home/ray/src/lock.txt" in body and " -e " not in body and "--editable" not in body
    assert not any(tool in body for tool in ("pytest", "[test]", "-r requirements"))
    job = next(d for d in _documents() if d["kind"] == "RayJob")
    groups = {g["groupName"]: g for g in job["spec"]["rayClusterSpec"]["workerGroupSpecs"]}
    (gpu,) = groups["learner-gpu"]["template"]["spec"]["containers"]
    assert gpu["image"].endswith("-cuda") and gpu["resources"]["limits"]["nvidia.com/gpu"] == "1"
