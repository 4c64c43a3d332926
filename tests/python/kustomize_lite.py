"""The subset of `kubectl kustomize` that deploy/ uses, so CI can build the overlays
without kubectl: `resources` (manifest files and base folders, recursively) and
`patches` given by `path` (strategic-merge patches whose target is the patch's own kind
and name). Anything else in a kustomization is an error, not silently ignored.

    kustomize_lite.py DIR                  # the built resources, as multi-document YAML
    kustomize_lite.py DIR --check-kubectl  # and compare them with `kubectl kustomize DIR`

Strategic merge as Kubernetes does it for the fields deploy/ patches: maps merge key by
key (a null value deletes the key); lists with a merge key (containers and volumes by
name, env by name, container ports by containerPort, volumeMounts by mountPath) merge
item by item, the patch's items first in the patch's order, then the base's other items
in theirs; other lists are replaced. `--check-kubectl` keeps the two honest where kubectl
is installed.

Exit status: 0 built (and equal to kubectl's output), 1 an error or a difference,
77 PyYAML (or, with --check-kubectl, kubectl) missing."""
import copy
import glob
import os
import shutil
import subprocess
import sys

try:
    import yaml
except ImportError as e:  # pragma: no cover
    print(f"PyYAML not installed: {e}", file=sys.stderr)
    sys.exit(77)

KUSTOMIZATION = "kustomization.yaml"
MERGE_KEYS = {
    "containers": "name",
    "initContainers": "name",
    "env": "name",
    "volumes": "name",
    "volumeMounts": "mountPath",
    "ports": "containerPort",
}
KNOWN_FIELDS = {"apiVersion", "kind", "resources", "patches"}


class KustomizeError(Exception):
    pass


def load_docs(path):
    with open(path) as f:
        return [d for d in yaml.safe_load_all(f) if d]


def resource_id(doc):
    return (doc["apiVersion"], doc["kind"], doc["metadata"]["name"])


def merge(base, patch, where):
    """`patch` strategically merged into `base` (neither is modified)."""
    if not isinstance(base, dict) or not isinstance(patch, dict):
        return copy.deepcopy(patch)
    out = copy.deepcopy(base)
    for key, value in patch.items():
        if key.startswith("$"):
            raise KustomizeError(f"{where}: patch directive {key} not supported")
        if value is None:
            out.pop(key, None)
        elif key in MERGE_KEYS and isinstance(value, list) and isinstance(out.get(key), list):
            out[key] = merge_list(out[key], value, MERGE_KEYS[key], f"{where}.{key}")
        elif key in out:
            out[key] = merge(out[key], value, f"{where}.{key}")
        else:
            out[key] = drop_nulls(value)
    return out


def merge_list(base, patch, merge_key, where):
    for item in base + patch:
        if not isinstance(item, dict) or merge_key not in item:
            raise KustomizeError(f"{where}: an item without its merge key {merge_key}")
    by_key = {item[merge_key]: item for item in base}
    patched = [merge(by_key.get(p[merge_key], {}), p, where) for p in patch]
    keys = {p[merge_key] for p in patch}
    return patched + [copy.deepcopy(b) for b in base if b[merge_key] not in keys]


def drop_nulls(value):
    if isinstance(value, dict):
        return {k: drop_nulls(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [drop_nulls(v) for v in value]
    return value


def build(folder):
    """(resources, extras): the kustomization's output, and the other manifests lying in
    the folders it reads (secret.example.yaml: applied by hand, not by kustomize)."""
    path = os.path.join(folder, KUSTOMIZATION)
    with open(path) as f:
        k = yaml.safe_load(f) or {}
    unknown = set(k) - KNOWN_FIELDS
    if unknown:
        raise KustomizeError(f"{path}: fields not supported here: {sorted(unknown)}")
    resources, extras, used = [], [], {os.path.abspath(path)}
    for r in k.get("resources", []):
        p = os.path.normpath(os.path.join(folder, r))
        if os.path.isdir(p):
            res, ext = build(p)
            resources += res
            extras += ext
        else:
            resources += load_docs(p)
            used.add(os.path.abspath(p))
    ids = [resource_id(d) for d in resources]
    if len(set(ids)) != len(ids):
        raise KustomizeError(f"{path}: a resource is defined twice: {ids}")
    for entry in k.get("patches", []):
        if set(entry) != {"path"}:
            raise KustomizeError(f"{path}: only `patches: - path: FILE` is supported: {entry}")
        p = os.path.normpath(os.path.join(folder, entry["path"]))
        used.add(os.path.abspath(p))
        for patch in load_docs(p):
            target = resource_id(patch)
            matches = [i for i, d in enumerate(resources) if resource_id(d) == target]
            if len(matches) != 1:
                raise KustomizeError(f"{p}: patch target {target} not found")
            i = matches[0]
            resources[i] = merge(resources[i], patch, f"{p}:{target[1]}/{target[2]}")
    for other in sorted(glob.glob(os.path.join(folder, "*.yaml"))):
        if os.path.abspath(other) not in used:
            extras += load_docs(other)
    return resources, extras


def by_id(docs):
    return {resource_id(d): d for d in docs}


def main(argv):
    if len(argv) not in (2, 3) or (len(argv) == 3 and argv[2] != "--check-kubectl"):
        print(__doc__, file=sys.stderr)
        return 1
    folder = argv[1]
    try:
        resources, _ = build(folder)
    except (KustomizeError, OSError, KeyError) as e:
        print(f"kustomize_lite: {e}", file=sys.stderr)
        return 1
    if len(argv) == 3:
        kubectl = shutil.which("kubectl")
        if kubectl is None:
            print("kubectl not installed", file=sys.stderr)
            return 77
        out = subprocess.run([kubectl, "kustomize", folder], capture_output=True, text=True)
        if out.returncode != 0:
            print(f"kubectl kustomize failed: {out.stderr}", file=sys.stderr)
            return 1
        theirs, ours = by_id(d for d in yaml.safe_load_all(out.stdout) if d), by_id(resources)
        if theirs != ours:
            for rid in sorted(set(theirs) | set(ours)):
                if theirs.get(rid) != ours.get(rid):
                    print(f"differs from kubectl kustomize: {rid}\n"
                          f"kubectl: {theirs.get(rid)}\nours:    {ours.get(rid)}",
                          file=sys.stderr)
            return 1
    sys.stdout.write(yaml.safe_dump_all(resources, sort_keys=False))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
