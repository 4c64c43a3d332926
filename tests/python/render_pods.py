"""Renders what the pods of a kustomization in deploy/ (deploy/k8s, or an overlay such as
deploy/k8s-gpu) run, built the way `kubectl apply -k` builds it (kustomize_lite.py): for
the coordinator Deployment and the worker Job, the image, the container args, the
environment (envFrom ConfigMaps/Secrets resolved from the manifests, `$(VAR)` references
kept, fieldRef/resourceFieldRef described), the resources, the tolerations and the files
mounted from ConfigMaps. Secrets come from the manifests beside the kustomizations
(secret.example.yaml). Prints JSON. Exit 77: PyYAML missing."""
import json
import os
import re
import sys

from kustomize_lite import KustomizeError, build

folder = sys.argv[1]
try:
    docs, extras = build(folder)
except KustomizeError as e:
    print(f"kustomize_lite: {e}", file=sys.stderr)
    sys.exit(1)

config_maps = {d["metadata"]["name"]: d.get("data", {}) for d in docs + extras
               if d["kind"] == "ConfigMap"}
secrets = {d["metadata"]["name"]: d.get("stringData", {}) for d in docs + extras
           if d["kind"] == "Secret"}
ENV_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def render(pod_spec):
    c = pod_spec["containers"][0]
    env = {}
    for ref in c.get("envFrom", []):
        if "configMapRef" in ref:
            source = config_maps[ref["configMapRef"]["name"]]
        else:
            source = secrets[ref["secretRef"]["name"]]
        # Kubernetes skips keys that are not valid variable names (job.toml).
        env.update({k: {"value": v} for k, v in source.items() if ENV_NAME.match(k)})
    for e in c.get("env", []):
        if "value" in e:
            env[e["name"]] = {"value": e["value"]}
        elif "fieldRef" in e["valueFrom"]:
            env[e["name"]] = {"fieldRef": e["valueFrom"]["fieldRef"]["fieldPath"]}
        else:
            r = e["valueFrom"]["resourceFieldRef"]
            limits = c["resources"]["limits"]
            env[e["name"]] = {"resourceFieldRef": r["resource"], "value": str(limits[r["resource"].split(".")[1]])}
    files = {}
    secret_files = {}
    volumes = {v["name"]: v for v in pod_spec.get("volumes", [])}
    for m in c.get("volumeMounts", []):
        v = volumes[m["name"]]
        if "configMap" in v:
            data = config_maps[v["configMap"]["name"]]
            for item in v["configMap"].get("items", [{"key": k, "path": k} for k in data]):
                files[os.path.join(m["mountPath"], item["path"])] = data[item["key"]]
        elif "secret" in v:
            # Secrets made by hand (no example values to show): "secret/key" per path.
            name = v["secret"]["secretName"]
            for item in v["secret"]["items"]:
                secret_files[os.path.join(m["mountPath"], item["path"])] = f"{name}/{item['key']}"
    probes = {kind: c[kind]["grpc"]["port"] for kind in ["readinessProbe", "livenessProbe"]
              if kind in c}
    return {"image": c["image"], "args": c.get("args", []), "env": env, "files": files,
            "secret_files": secret_files, "probes": probes,
            "ports": [p["containerPort"] for p in c.get("ports", [])],
            "resources": c.get("resources", {}),
            "tolerations": pod_spec.get("tolerations", [])}


out = {}
for d in docs:
    if d["kind"] == "Deployment" and d["metadata"]["name"] == "osrt-coordinator":
        out["coordinator"] = render(d["spec"]["template"]["spec"])
    if d["kind"] == "Job" and d["metadata"]["name"] == "osrt-workers":
        out["worker"] = render(d["spec"]["template"]["spec"])
        out["worker"]["parallelism"] = d["spec"]["parallelism"]
print(json.dumps(out, indent=2))
