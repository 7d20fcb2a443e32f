"""The deployment manifests under docker/k8s/ against the Kubernetes schema (kubernetes-validate, strict:
an unknown or misspelled field fails) and against the project they deploy (routes, port, user,
settings, memory budget)."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest

from neumip.server.settings import Settings

kv = pytest.importorskip("kubernetes_validate", reason="needs kubernetes-validate (pip install 'neumip[deploy]')")
yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parents[2]
K8S = ROOT / "docker" / "k8s"
VERSION = "1.37.0"

# KServe's own fields (serving.kserve.io/v1beta1), beside the Kubernetes types they embed inline:
# PredictorSpec = PodSpec + ComponentExtensionSpec + model; ModelSpec = Container + these.
KSERVE_MODEL_FIELDS = {"modelFormat", "runtime", "protocolVersion", "storageUri", "storage"}
KSERVE_COMPONENT_FIELDS = {"minReplicas", "maxReplicas", "scaleTarget", "scaleMetric", "scaleMetricType",
                           "containerConcurrency", "timeout", "canaryTrafficPercent", "logger", "batcher",
                           "labels", "annotations", "deploymentStrategy", "autoScaling"}


def load(name: str) -> dict[str, dict]:
    return {doc["kind"]: doc for doc in yaml.safe_load_all((K8S / name).read_text())}


def validate(doc: dict) -> None:
    kv.validate(doc, VERSION, strict=True)


@pytest.fixture(scope="module")
def neumip() -> dict[str, dict]:
    return load("neumip.yaml")


def container(docs: dict[str, dict]) -> dict:
    (server,) = docs["Deployment"]["spec"]["template"]["spec"]["containers"]
    return server


def test_deployment_service_and_autoscaler_are_valid(neumip):
    assert set(neumip) == {"Deployment", "Service", "HorizontalPodAutoscaler"}
    for doc in neumip.values():
        validate(doc)


@pytest.mark.parametrize("edit", ["misspelled field", "wrong type"])
def test_the_validation_catches_mistakes(neumip, edit):
    bad = copy.deepcopy(neumip["Deployment"])
    server = container({"Deployment": bad})
    if edit == "misspelled field":
        server["readinesProbe"] = server.pop("readinessProbe")
    else:
        server["resources"]["limits"]["memory"] = ["2Gi"]
    with pytest.raises(kv.ValidationError):
        validate(bad)


def test_deployment_matches_the_server(neumip):
    from neumip.server.app import create_app

    routes = set(create_app(Settings()).openapi()["paths"])
    server = container(neumip)
    assert server["readinessProbe"]["httpGet"]["path"] == "/v2/health/ready" in routes
    assert server["livenessProbe"]["httpGet"]["path"] == "/v2/health/live" in routes
    assert server["ports"] == [{"name": "http", "containerPort": Settings().port}]
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    uid = re.search(r"--uid (\d+)", dockerfile).group(1)
    assert neumip["Deployment"]["spec"]["template"]["spec"]["securityContext"]["runAsUser"] == int(uid)
    env = {e["name"]: e["value"] for e in server["env"]}
    assert all(name.removeprefix("NEUMIP_").lower() in Settings.model_fields for name in env)
    Settings(**{k.removeprefix("NEUMIP_").lower(): v for k, v in env.items()})  # the values are valid settings
    # one ONNX Runtime worker per CPU of the pod (the server would count the node's cores)
    assert int(env["NEUMIP_ORT_WORKERS"]) * int(env["NEUMIP_ORT_THREADS"]) == int(server["resources"]["limits"]["cpu"])
    # the pod's memory limit is compose's (whose comment gives the budget)
    compose = (ROOT / "compose.yaml").read_text()
    assert re.search(r"NEUMIP_MEMORY_LIMIT:-(\d+)g", compose).group(1) + "Gi" == server["resources"]["limits"]["memory"]
    service, hpa = neumip["Service"], neumip["HorizontalPodAutoscaler"]
    assert service["spec"]["selector"] == neumip["Deployment"]["spec"]["selector"]["matchLabels"]
    assert hpa["spec"]["scaleTargetRef"]["name"] == neumip["Deployment"]["metadata"]["name"]


def kserve_pod(isvc: dict) -> dict:
    """The Pod KServe makes of the predictor: its PodSpec fields, and the model's Container fields."""
    predictor = copy.deepcopy(isvc["spec"]["predictor"])
    model = predictor.pop("model")
    pod_fields = {k: v for k, v in predictor.items() if k not in KSERVE_COMPONENT_FIELDS}
    container_fields = {k: v for k, v in model.items() if k not in KSERVE_MODEL_FIELDS}
    return {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": "predictor"},
            "spec": {**pod_fields, "containers": [{"name": "kserve-container", **container_fields}]}}


def test_kserve_inference_service():
    (isvc,) = load("kserve-inferenceservice.yaml").values()
    assert (isvc["apiVersion"], isvc["kind"]) == ("serving.kserve.io/v1beta1", "InferenceService")
    model = isvc["spec"]["predictor"]["model"]
    assert model["modelFormat"] == {"name": "triton"} and model["protocolVersion"] == "v2"
    assert re.match(r"^(s3|gs|pvc|https?)://", model["storageUri"])
    validate(kserve_pod(isvc))
    bad = copy.deepcopy(isvc)
    bad["spec"]["predictor"]["model"]["storageURI"] = bad["spec"]["predictor"]["model"].pop("storageUri")
    with pytest.raises(kv.ValidationError):  # a misspelled KServe field is no Container field either
        validate(kserve_pod(bad))
