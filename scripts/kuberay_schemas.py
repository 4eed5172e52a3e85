"""Extract KubeRay's RayJob and RayCluster schemas (ray.io/v1) from the operator's CRDs.

    python scripts/kuberay_schemas.py KUBERAY_CHECKOUT TAG

reads ``ray-operator/config/crd/bases/ray.io_{rayjobs,rayclusters}.yaml`` at git tag TAG of a
clone of https://github.com/ray-project/kuberay and writes each version ``v1``'s
``openAPIV3Schema`` to ``deploy/schemas/<kind>-v1.schema.json.gz`` with its source recorded in
``deploy/schemas/SOURCE.json``; ``tests/test_deploy.py`` validates the manifests against them.
"""

import gzip
import json
import subprocess
import sys
from pathlib import Path

import yaml

OUT = Path(__file__).resolve().parents[1] / "deploy" / "schemas"
FILES = {"RayJob": "ray.io_rayjobs.yaml", "RayCluster": "ray.io_rayclusters.yaml"}


def main(checkout: str, tag: str) -> None:
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", checkout, *args], check=True, capture_output=True, text=True).stdout

    commit = git("rev-parse", f"{tag}^{{commit}}").strip()
    source = {"repository": "https://github.com/ray-project/kuberay", "tag": tag, "commit": commit, "files": {}}
    for kind, name in FILES.items():
        path = f"ray-operator/config/crd/bases/{name}"
        crd = yaml.safe_load(git("show", f"{commit}:{path}"))
        (version,) = [v for v in crd["spec"]["versions"] if v["name"] == "v1"]
        schema = version["schema"]["openAPIV3Schema"]
        out = OUT / f"{kind.lower()}-v1.schema.json.gz"
        out.write_bytes(gzip.compress(json.dumps(schema, sort_keys=True, separators=(",", ":")).encode(), mtime=0))
        source["files"][out.name] = {"path": path, "crd": crd["metadata"]["name"], "version": "v1"}
    (OUT / "SOURCE.json").write_text(json.dumps(source, indent=2) + "\n")


if __name__ == "__main__":
    main(*sys.argv[1:3])
