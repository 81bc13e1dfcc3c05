"""Execution profiles (flows/profiles.py): every kind of infra/ loads, bad profiles are refused in one line
naming the file, the key and the fix, exposure warnings per kind, and the Kubernetes spec."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from flows.profiles import DEFAULT_PROFILE, ProfileError, exposure_warnings, load_profile

INFRA = DEFAULT_PROFILE.parent


def test_default_profile_is_a_two_worker_local_cluster():
    profile = load_profile(DEFAULT_PROFILE)
    assert profile.cluster["kind"] == "local"
    assert (profile.cluster["n_workers"], profile.cluster["threads_per_worker"]) == (2, 1)
    assert profile.prefect["api_url"] is None


def test_profile_errors_name_the_file(tmp_path):
    with pytest.raises(ProfileError, match="does not exist"):
        load_profile(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("cluster: [unclosed\n")
    with pytest.raises(ProfileError, match=r"bad\.yaml is not valid YAML"):
        load_profile(bad)
    yarn = tmp_path / "yarn.yaml"
    yarn.write_text("cluster: {kind: yarn}\n")
    # refused when loaded, before Prefect or a cluster starts (it used to be refused by dask_client)
    with pytest.raises(ProfileError, match=r"yarn\.yaml: cluster kind 'yarn' is not supported; set 'cluster.kind' to "
                       r"one of local, address, slurm, pbs, kubernetes"):
        load_profile(yarn)
    assert issubclass(ProfileError, ValueError)  # the CLI's bad input


@pytest.mark.parametrize("text, message", [
    # a typo used to reach LocalCluster(**spec), after Prefect had started
    ("cluster: {kind: local, n_worker: 4}\n",
     "unknown key 'cluster.n_worker' for cluster kind 'local'; allowed keys: kind, n_workers, threads_per_worker, "
     "memory_limit, processes, dashboard, host, dashboard_address"),
    ("cluster: {kind: local, scheduler_kwargs: {dashboard: true}}\n", "unknown key 'cluster.scheduler_kwargs'"),
    ("prefect: {api_url: null, startup_timeout: 30}\n",
     "unknown key 'prefect.startup_timeout'; allowed keys: api_url, startup_timeout_s"),
    ("clusters: {kind: local}\n", "unknown section 'clusters'; allowed sections: cluster, prefect"),
    ("cluster: {n_workers: two}\n", "'cluster.n_workers' must be an integer, not 'two' (str)"),
    ("cluster: {n_workers: true}\n", "'cluster.n_workers' must be an integer, not True (bool)"),
    ("cluster: {n_workers: 0}\n", "'cluster.n_workers' must be at least 1, not 0"),
    ("cluster: {dashboard: 'yes please'}\n", "'cluster.dashboard' must be true or false"),
    ("cluster: {dashboard_address: 8787}\n", "'cluster.dashboard_address' must be a string, not 8787 (int)"),
    ("cluster: {memory_limit: 4 apples}\n", "'cluster.memory_limit' must be a size like 4GiB"),
    ("prefect: {startup_timeout_s: soon}\n", "'prefect.startup_timeout_s' must be a number, not 'soon' (str)"),
    ("prefect: {api_url: 8080}\n", "'prefect.api_url' must be a string or null"),
    ("cluster: [local]\n", "'cluster' must be a mapping of keys"),
    # safe_load refuses python tags; the message used to span four lines of PyYAML's marks
    ("cluster: !!python/object/apply:os.system ['touch pwned']\n",
     "is not valid YAML (line 1, column 10: could not determine a constructor for the tag "
     "'tag:yaml.org,2002:python/object/apply:os.system')"),
])
def test_a_profile_is_validated_against_its_cluster_kind_when_loaded(tmp_path, text, message):
    path = tmp_path / "profile.yaml"
    path.write_text(text)
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    assert str(info.value).startswith(f"execution profile {path}")
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_only_a_profile_that_binds_beyond_loopback_without_tls_is_warned(tmp_path):
    import dask

    def profile(text):
        path = tmp_path / "p.yaml"
        path.write_text(text)
        return load_profile(path)

    assert exposure_warnings(load_profile(DEFAULT_PROFILE)) == []
    assert exposure_warnings(profile("cluster: {dashboard: true}\n")) == []      # 127.0.0.1:8787
    assert exposure_warnings(profile("cluster: {host: localhost, dashboard_address: '[::1]:8787'}\n")) == []
    public = profile("cluster: {host: 0.0.0.0, dashboard: true}\n")
    lines = exposure_warnings(public)
    assert len(lines) == 2 and all("\n" not in line and str(public.path) in line for line in lines)
    assert "scheduler and workers listen on 0.0.0.0 (cluster.host) without TLS" in lines[0]
    assert "HTTP server" in lines[1] and "0.0.0.0:8787" in lines[1]
    dashboard = exposure_warnings(profile("cluster: {dashboard: true, dashboard_address: ':8787'}\n"))
    assert len(dashboard) == 1 and "listens on :8787 without TLS" in dashboard[0]
    with dask.config.set({"distributed.comm.require-encryption": True,
                          "distributed.scheduler.dashboard.tls.cert": "cert.pem"}):
        assert exposure_warnings(public) == []
    assert len(exposure_warnings(profile("cluster: {host: 'tls://0.0.0.0'}\n"))) == 1   # its HTTP server has no TLS


@pytest.mark.parametrize("name, kind", [("local.yaml", "local"), ("address.yaml", "address"), ("slurm.yaml", "slurm"),
                                        ("pbs.yaml", "pbs"), ("kubernetes.yaml", "kubernetes")])
def test_every_shipped_profile_loads_as_its_kind(name, kind):
    profile = load_profile(INFRA / name)
    assert profile.kind == kind and profile.record() == {"path": str(INFRA / name), "cluster": profile.cluster}


def _pem(tmp_path: Path) -> str:
    for name in ("ca.pem", "cert.pem", "key.pem"):
        (tmp_path / name).write_text("-----BEGIN CERTIFICATE-----\n")
    return "{ca_file: ca.pem, cert_file: cert.pem, key_file: key.pem}"


SLURM = "cluster: {kind: slurm, cores: 1, memory: 2GiB, "


@pytest.mark.parametrize("text, key, message", [
    ("cluster: {kind: slurm, cores: 1, memory: 2GiB, nodes: 4}\n", "cluster.nodes",
     "unknown key 'cluster.nodes' for cluster kind 'slurm'; allowed keys: kind, cores, memory"),
    (SLURM + "walltime: 3600}\n", "cluster.walltime", "'cluster.walltime' must be a string, not 3600 (int)"),
    (SLURM + "walltime: one hour}\n", "cluster.walltime", "must be a job time limit HH:MM:SS or D-HH:MM:SS"),
    (SLURM + "minimum_jobs: 3, maximum_jobs: 2}\n", "cluster.minimum_jobs",
     "'cluster.minimum_jobs' (3) is above 'cluster.maximum_jobs' (2); set minimum_jobs <= maximum_jobs"),
    (SLURM + "processes: 2}\n", "cluster.processes", "'cluster.processes' (2) must not exceed 'cluster.cores' (1)"),
    (SLURM + "job_extra_directives: --qos=low}\n", "cluster.job_extra_directives",
     "'cluster.job_extra_directives' must be a list of strings"),
    (SLURM + "job_extra_directives: [--qos=low, 4]}\n", "cluster.job_extra_directives", "must be a list of strings"),
    ("cluster: {kind: slurm, cores: 1}\n", "cluster.memory",
     "cluster kind 'slurm' needs 'cluster.memory' (required: cores, memory); see infra/slurm.yaml"),
    (SLURM.replace("2GiB", "lots") + "queue: debug}\n", "cluster.memory",
     "'cluster.memory' must be a size like 4GiB (per job)"),
    ("cluster: {kind: address, address: '127.0.0.1:8786'}\n", "cluster.address",
     "'cluster.address' must be a scheduler address tcp://HOST:PORT or tls://HOST:PORT"),
    ("cluster: {kind: address, address: 'http://127.0.0.1:8786'}\n", "cluster.address", "tcp://HOST:PORT"),
    ("cluster: {kind: address, address: 'tls://10.0.0.5:8786'}\n", "cluster.address",
     "is tls://10.0.0.5:8786 (TLS) but the profile has no 'cluster.security'"),
    ("cluster: {kind: address}\n", "cluster.address", "cluster kind 'address' needs 'cluster.address'"),
    ("cluster: {kind: address, address: 'tls://h:1', security: {ca_file: ca.pem}}\n", "cluster.security",
     "'cluster.security' needs ca_file, cert_file, key_file (PEM files of the Dask TLS setup); 'cert_file' is missing"),
    ("cluster: {kind: address, address: 'tls://h:1', security: {ca_file: nope.pem, cert_file: c, key_file: k}}\n",
     "cluster.security.ca_file", "which does not exist; give an absolute path or one relative to the profile's folder"),
    ("cluster: {kind: address, address: 'tcp://h:1', security: {ca: x}}\n", "cluster.security.ca",
     "unknown key 'cluster.security.ca'; allowed keys: ca_file, cert_file, key_file"),
    ("cluster: {kind: kubernetes, n_workers: 2}\n", "cluster.image", "cluster kind 'kubernetes' needs 'cluster.image'"),
    ("cluster: {kind: kubernetes, image: btf, name: My_Cluster}\n", "cluster.name", "must be a Kubernetes name"),
    ("cluster: {kind: kubernetes, image: btf, resources: {request: {cpu: 1}}}\n", "cluster.resources.request",
     "resources holds requests and limits"),
    ("cluster: {kind: kubernetes, image: btf, host: 0.0.0.0}\n", "cluster.host",
     "unknown key 'cluster.host' for cluster kind 'kubernetes'"),
    ("cluster: {kind: [slurm]}\n", "cluster.kind", "cluster kind ['slurm'] is not supported; set 'cluster.kind' to"),
    ("cluster: !!python/name:os.system {kind: slurm}\n", "line 1", "is not valid YAML (line 1, column 10"),
])
def test_a_bad_profile_of_any_kind_is_refused_in_one_line_naming_file_key_and_fix(tmp_path, text, key, message):
    path = tmp_path / "profile.yaml"
    path.write_text(text)
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    line = str(info.value)
    assert line.startswith(f"execution profile {path}") and "\n" not in line
    assert key in line and message in line, line


def test_profile_paths_are_taken_from_the_profile_folder_and_made_absolute(tmp_path):
    path = tmp_path / "tls.yaml"
    path.write_text(f"cluster: {{kind: address, address: 'tls://10.0.0.5:8786', security: {_pem(tmp_path)}}}\n")
    security = load_profile(path).cluster["security"]
    assert security == {key: str(tmp_path / f"{name}.pem") for key, name in
                        (("ca_file", "ca"), ("cert_file", "cert"), ("key_file", "key"))}
    path.write_text(SLURM + "log_directory: logs, local_directory: /scratch}\n")
    cluster = load_profile(path).cluster
    assert (cluster["log_directory"], cluster["local_directory"]) == (str(tmp_path / "logs"), "/scratch")


def test_new_kinds_are_warned_when_they_reach_beyond_this_machine_without_tls(tmp_path):
    def warnings(text):
        path = tmp_path / "p.yaml"
        path.write_text(text)
        return exposure_warnings(load_profile(path))

    assert warnings("cluster: {kind: address, address: 'tcp://127.0.0.1:8786'}\n") == []
    remote = warnings("cluster: {kind: address, address: 'tcp://10.0.0.5:8786'}\n")
    assert len(remote) == 1 and "tcp://10.0.0.5:8786 (cluster.address)" in remote[0] and "tls://" in remote[0]
    assert warnings(f"cluster: {{kind: address, address: 'tls://10.0.0.5:8786', security: {_pem(tmp_path)}}}\n") == []
    assert warnings(SLURM + "interface: lo}\n") == []
    ib0 = warnings(SLURM + "interface: ib0}\n")
    assert len(ib0) == 1 and "interface ib0 (cluster.interface) without TLS" in ib0[0]
    assert warnings(SLURM + f"interface: ib0, security: {_pem(tmp_path)}}}\n") == []
    http = warnings(SLURM + "interface: lo, dashboard: true, dashboard_address: '0.0.0.0:8787'}\n")
    assert len(http) == 1 and "0.0.0.0:8787 (cluster.dashboard_address)" in http[0]
    assert warnings("cluster: {kind: kubernetes, image: btf}\n") == []


def test_btf_cluster_spec_prints_the_kubernetes_resource_with_the_worker_environment(capsys):
    """The bar: `btf cluster spec infra/kubernetes.yaml` prints a DaskCluster resource that parses."""
    from flows.cli import main
    from flows.runtime import WORKER_ENVIRON

    assert main(["cluster", "spec", str(INFRA / "kubernetes.yaml")]) == 0
    resource = yaml.safe_load(capsys.readouterr().out)
    assert (resource["apiVersion"], resource["kind"]) == ("kubernetes.dask.org/v1", "DaskCluster")
    assert resource["metadata"] == {"name": "btf", "namespace": "btf"}
    worker = resource["spec"]["worker"]
    assert worker["replicas"] == 4
    container = worker["spec"]["containers"][0]
    assert container["image"] == "registry.example.org/btf-pipeline:0.1.0"
    assert container["args"][:4] == ["dask", "worker", "--nthreads", "1"]
    assert container["resources"] == {"requests": {"cpu": "1", "memory": "4Gi"},
                                      "limits": {"cpu": "1", "memory": "4Gi"}}
    env = {item["name"]: item["value"] for item in container["env"]}
    assert {key: env[key] for key in WORKER_ENVIRON} == WORKER_ENVIRON
    assert env["PREFECT_API_URL"] == "http://prefect-server.btf.svc:4200/api"
    scheduler = resource["spec"]["scheduler"]["spec"]["containers"][0]
    assert scheduler["image"] == container["image"] and scheduler["args"][0] == "dask-scheduler"
    assert main(["cluster", "spec", str(INFRA / "slurm.yaml")]) == 2          # not a kubernetes profile
    assert "cluster kind is 'slurm'" in capsys.readouterr().err
