"""Execution profiles: which Dask cluster and Prefect API a ``btf`` run uses, loaded and checked in one place.

A profile is a YAML file with two sections, ``cluster:`` and ``prefect:`` (``infra/*.yaml``, one per cluster
kind, each commented key by key; docs/clusters.md). :func:`load_profile` refuses, before Prefect or a cluster
starts, every key its cluster kind does not know, every value of the wrong type or range, YAML tags, and files
a profile names that do not exist, each with one line that names the file, the key and the fix (the CLI exits
2). :func:`exposure_warnings` names the sockets a profile opens beyond this machine without TLS
(docs/architecture.md, "Execution"; docs/clusters.md, "Security").
"""

from __future__ import annotations

import ipaddress
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from flows.server import LOOPBACK

DEFAULT_PROFILE = Path(__file__).resolve().parents[1] / "infra" / "local.yaml"


class ProfileError(ValueError):
    """An execution profile is missing, not YAML, or names a key, type or cluster kind that does not
    exist; the one-line message names the file and the key and says what is allowed (bad input: the
    CLI exits ``EXIT_BAD_INPUT`` before Prefect or a cluster starts)."""


@dataclass(frozen=True)
class Profile:
    """A parsed and validated execution profile (see ``infra/*.yaml``); build it with
    :func:`load_profile`, which refuses what a cluster kind does not know. Paths in ``cluster``
    (``security`` files, ``log_directory``, ``local_directory``) are absolute."""

    path: str
    cluster: dict[str, Any] = field(default_factory=dict)
    prefect: dict[str, Any] = field(default_factory=dict)

    @property
    def kind(self) -> str:
        """The cluster kind: ``local``, ``address``, ``slurm``, ``pbs`` or ``kubernetes``."""
        return self.cluster.get("kind", "local")

    def record(self) -> dict[str, Any]:
        """What a run's ``report.json`` records of its profile: the file and its ``cluster:`` section."""
        return {"path": self.path, "cluster": dict(self.cluster)}


_INT = (int,)
_NUMBER = (int, float)
_STR = (str,)
_BOOL = (bool,)
_LIST = (list,)
_MAP = (dict,)
_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false", type(None): "null",
               list: "a list of strings", dict: "a mapping"}

#: The keys of a ``security:`` mapping (kinds ``address``, ``slurm``, ``pbs``): PEM files of a Dask TLS setup
#: (docs/clusters.md, "Security"). A relative path is taken from the profile file's folder.
SECURITY_KEYS: dict[str, tuple[type, ...]] = {"ca_file": _STR, "cert_file": _STR, "key_file": _STR}

#: Keys of the job-queue kinds (``slurm``: ``dask_jobqueue.SLURMCluster``; ``pbs``: ``PBSCluster``, the
#: same code path); ``infra/slurm.yaml`` explains each one.
_JOBQUEUE_KEYS: dict[str, tuple[type, ...]] = {
    "kind": _STR,
    "cores": _INT,                    # cores per job
    "memory": _STR,                   # memory per job, "4GiB"
    "processes": _INT,                # worker processes per job (each gets cores / processes threads)
    "walltime": _STR,                 # "HH:MM:SS" or "D-HH:MM:SS"
    "queue": _STR,                    # partition (slurm) or queue (pbs)
    "account": _STR,
    "job_extra_directives": _LIST,    # more #SBATCH / #PBS lines, e.g. "--qos=normal"
    "job_script_prologue": _LIST,     # shell lines before the worker starts, e.g. "module load python/3.11"
    "interface": _STR,                # network interface of the scheduler and workers (lo, ib0, eth0)
    "log_directory": _STR,
    "local_directory": _STR,          # worker spill folder, node-local
    "python": _STR,                   # interpreter on the compute nodes [this one]
    "minimum_jobs": _INT,             # adaptive scaling between these two
    "maximum_jobs": _INT,
    "dashboard": _BOOL,
    "dashboard_address": _STR,
    "security": _MAP,
}

#: The keys of a profile's ``cluster:`` section, per cluster kind, with the types their values may have;
#: ``infra/<kind>.yaml`` explains each key. Each kind has its starter in ``flows.runtime``.
CLUSTER_KEYS: dict[str, dict[str, tuple[type, ...]]] = {
    "local": {
        "kind": _STR,
        "n_workers": _INT,
        "threads_per_worker": _INT,
        "memory_limit": (str, int),       # "4GiB", bytes, or "auto"
        "processes": _BOOL,
        "dashboard": _BOOL,
        "host": _STR,                     # interface of the scheduler, nannies and workers [127.0.0.1]
        "dashboard_address": _STR,        # host:port of the scheduler's HTTP server [<host>:8787 or :0]
    },
    "address": {
        "kind": _STR,
        "address": _STR,                  # tcp://host:port or tls://host:port of a running scheduler
        "security": _MAP,
        "timeout_s": _NUMBER,             # how long to wait for the scheduler and its first worker [60]
    },
    "slurm": _JOBQUEUE_KEYS,
    "pbs": _JOBQUEUE_KEYS,
    "kubernetes": {
        "kind": _STR,
        "name": _STR,                     # name of the DaskCluster resource [btf]
        "namespace": _STR,
        "image": _STR,                    # a container image with this project installed
        "n_workers": _INT,
        "threads_per_worker": _INT,
        "resources": _MAP,                # {requests: {cpu, memory}, limits: {cpu, memory}} per pod
    },
}

#: Keys a cluster kind cannot do without.
REQUIRED_KEYS: dict[str, tuple[str, ...]] = {"address": ("address",), "slurm": ("cores", "memory"),
                                            "pbs": ("cores", "memory"), "kubernetes": ("image",)}

#: The keys of a profile's ``prefect:`` section (every cluster kind).
PREFECT_KEYS: dict[str, tuple[type, ...]] = {
    "api_url": (str, type(None)),
    "startup_timeout_s": _NUMBER,
}

_WALLTIME = re.compile(r"^(\d+-)?\d{1,3}:\d{2}:\d{2}$")


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """One line for a YAML error: its problem and where (PyYAML's own text spans several lines)."""
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return " ".join(f"{where}{problem}".split())


def _check_section(path: Path, section: str, values: Any, allowed: dict[str, tuple[type, ...]],
                   what: str) -> dict[str, Any]:
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ProfileError(f"execution profile {path}: '{section}' must be a mapping of keys "
                           f"({', '.join(allowed)}), not {type(values).__name__}")
    for key, value in values.items():
        if key not in allowed:
            raise ProfileError(f"execution profile {path}: unknown key '{section}.{key}'{what}; "
                               f"allowed keys: {', '.join(allowed)}")
        types = allowed[key]
        if (not isinstance(value, types) or (isinstance(value, bool) and bool not in types)
                or (isinstance(value, list) and not all(isinstance(v, str) for v in value))):
            expected = " or ".join(_TYPE_NAMES[t] for t in types if not (t is int and float in types))
            raise ProfileError(f"execution profile {path}: '{section}.{key}' must be {expected}, "
                               f"not {value!r} ({type(value).__name__})")
    return dict(values)


def _fail(path: Path, key: str, must: str, value: Any) -> ProfileError:
    return ProfileError(f"execution profile {path}: '{key}' must be {must}, not {value!r}")


def _check_size(path: Path, key: str, value: Any, allow_auto: bool) -> None:
    from dask.utils import parse_bytes

    if allow_auto and value == "auto":
        return
    try:
        if parse_bytes(value) <= 0:
            raise ValueError("not positive")
    except (ValueError, TypeError):
        raise _fail(path, key, "a size like 4GiB" + (" (per worker), a number of bytes or auto" if allow_auto
                                                     else " (per job)"), value) from None


def _resolve(path: Path, value: str) -> Path:
    """A path of the profile: ``~`` expanded, a relative one taken from the profile file's folder."""
    candidate = Path(value).expanduser()
    return candidate if candidate.is_absolute() else (path.resolve().parent / candidate)


def _check_security(path: Path, cluster: dict[str, Any]) -> None:
    """Check ``cluster.security`` (every key, every file exists) and make its paths absolute."""
    if "security" not in cluster:
        return
    security = _check_section(path, "cluster.security", cluster["security"], SECURITY_KEYS, "")
    missing = [key for key in SECURITY_KEYS if key not in security]
    if missing:
        raise ProfileError(f"execution profile {path}: 'cluster.security' needs {', '.join(SECURITY_KEYS)} "
                           f"(PEM files of the Dask TLS setup); '{missing[0]}' is missing (docs/clusters.md, "
                           "'Security')")
    for key, value in security.items():
        file = _resolve(path, value)
        if not file.is_file():
            raise ProfileError(f"execution profile {path}: 'cluster.security.{key}' names {file}, which does not "
                               "exist; give an absolute path or one relative to the profile's folder")
        security[key] = str(file)
    cluster["security"] = security


def _check_local(path: Path, cluster: dict[str, Any]) -> None:
    for key in ("n_workers", "threads_per_worker"):
        if key in cluster and cluster[key] < 1:
            raise ProfileError(f"execution profile {path}: 'cluster.{key}' must be at least 1, not {cluster[key]}")
    if "memory_limit" in cluster:
        _check_size(path, "cluster.memory_limit", cluster["memory_limit"], allow_auto=True)


def _check_address(path: Path, cluster: dict[str, Any]) -> None:
    address = cluster["address"]
    if not re.match(r"^(tcp|tls)://[^/\s]+:\d+$", address):
        raise _fail(path, "cluster.address", "a scheduler address tcp://HOST:PORT or tls://HOST:PORT", address)
    if address.startswith("tls://") and "security" not in cluster:
        raise ProfileError(f"execution profile {path}: 'cluster.address' is {address} (TLS) but the profile has "
                           "no 'cluster.security' (ca_file, cert_file, key_file); add it or use tcp://")
    if "timeout_s" in cluster and not cluster["timeout_s"] > 0:
        raise _fail(path, "cluster.timeout_s", "a number of seconds above 0", cluster["timeout_s"])


def _check_jobqueue(path: Path, cluster: dict[str, Any]) -> None:
    for key in ("cores", "processes", "maximum_jobs"):
        if key in cluster and cluster[key] < 1:
            raise _fail(path, f"cluster.{key}", "at least 1", cluster[key])
    if cluster.get("processes", 1) > cluster["cores"]:
        raise ProfileError(f"execution profile {path}: 'cluster.processes' ({cluster['processes']}) must not exceed "
                           f"'cluster.cores' ({cluster['cores']}): each worker process needs a core")
    if cluster.get("minimum_jobs", 0) < 0:
        raise _fail(path, "cluster.minimum_jobs", "0 or more", cluster["minimum_jobs"])
    low, high = cluster.get("minimum_jobs", 1), cluster.get("maximum_jobs", 1)
    if low > high:
        raise ProfileError(f"execution profile {path}: 'cluster.minimum_jobs' ({low}) is above "
                           f"'cluster.maximum_jobs' ({high}); set minimum_jobs <= maximum_jobs")
    _check_size(path, "cluster.memory", cluster["memory"], allow_auto=False)
    if "walltime" in cluster and not _WALLTIME.match(cluster["walltime"]):
        raise _fail(path, "cluster.walltime", "a job time limit HH:MM:SS or D-HH:MM:SS", cluster["walltime"])
    for key in ("log_directory", "local_directory"):
        if key in cluster:
            cluster[key] = str(_resolve(path, cluster[key]))


def _check_kubernetes(path: Path, cluster: dict[str, Any]) -> None:
    for key in ("n_workers", "threads_per_worker"):
        if key in cluster and cluster[key] < 1:
            raise _fail(path, f"cluster.{key}", "at least 1", cluster[key])
    if "name" in cluster and not re.match(r"^[a-z0-9]([-a-z0-9]{0,38}[a-z0-9])?$", cluster["name"]):
        raise _fail(path, "cluster.name", "a Kubernetes name (lower-case letters, digits and '-')", cluster["name"])
    resources = cluster.get("resources", {})
    for part, amounts in resources.items():
        if part not in ("requests", "limits") or not isinstance(amounts, dict) or not all(
                key in ("cpu", "memory") and isinstance(v, (str, int, float)) for key, v in amounts.items()):
            raise ProfileError(f"execution profile {path}: 'cluster.resources.{part}' is not allowed; resources "
                               "holds requests and limits, each a mapping of cpu and memory (e.g. cpu: 1, "
                               "memory: 4Gi)")


_KIND_CHECKS = {"local": _check_local, "address": _check_address, "slurm": _check_jobqueue,
                "pbs": _check_jobqueue, "kubernetes": _check_kubernetes}


def _check_values(path: Path, cluster: dict[str, Any], prefect: dict[str, Any]) -> None:
    kind = cluster.get("kind", "local")
    missing = [key for key in REQUIRED_KEYS.get(kind, ()) if key not in cluster]
    if missing:
        raise ProfileError(f"execution profile {path}: cluster kind {kind!r} needs 'cluster.{missing[0]}' "
                           f"(required: {', '.join(REQUIRED_KEYS[kind])}); see infra/{kind}.yaml")
    _check_security(path, cluster)
    _KIND_CHECKS[kind](path, cluster)
    if "startup_timeout_s" in prefect and not prefect["startup_timeout_s"] > 0:
        raise ProfileError(f"execution profile {path}: 'prefect.startup_timeout_s' must be a number of "
                           f"seconds above 0, not {prefect['startup_timeout_s']!r}")


def load_profile(path: str | os.PathLike | None = None) -> Profile:
    """Read and validate an execution profile; ``None`` means ``$BTF_CLUSTER_CONFIG`` or the default.

    This is the one place a profile is checked: every key must exist for its section and cluster kind
    (``CLUSTER_KEYS``, ``PREFECT_KEYS``), have a value of its type and range, and every file it names
    must exist, so that a typo is named before Prefect or a cluster starts instead of reaching Dask.

    Raises
    ------
    ProfileError
        The file is missing or unreadable, not YAML (``!!python/...`` tags included), or names an
        unknown section, key or cluster kind, a value of the wrong type or range, or a file that does
        not exist; the message is one line that names the file, the key and the fix.
    """
    path = Path(path or os.environ.get("BTF_CLUSTER_CONFIG") or DEFAULT_PROFILE)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ProfileError(
            f"execution profile {path} does not exist; pass --cluster with a file "
            f"shaped like {DEFAULT_PROFILE}"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"execution profile {path} cannot be read: {exc}; pass --cluster with a readable "
                           "YAML file") from None
    except yaml.YAMLError as exc:
        raise ProfileError(f"execution profile {path} is not valid YAML ({_yaml_problem(exc)}); a profile holds "
                           f"plain keys and values only, shaped like {DEFAULT_PROFILE}") from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ProfileError(f"execution profile {path}: expected a mapping with 'cluster' and 'prefect' "
                           f"sections, not {type(data).__name__}")
    unknown = [key for key in data if key not in ("cluster", "prefect")]
    if unknown:
        raise ProfileError(f"execution profile {path}: unknown section '{unknown[0]}'; "
                           "allowed sections: cluster, prefect")
    raw_cluster = data.get("cluster") or {}
    kind = raw_cluster.get("kind", "local") if isinstance(raw_cluster, dict) else "local"
    if not isinstance(kind, str) or kind not in CLUSTER_KEYS:
        raise ProfileError(
            f"execution profile {path}: cluster kind {kind!r} is not supported; set 'cluster.kind' to one of "
            f"{', '.join(CLUSTER_KEYS)} (examples: infra/<kind>.yaml)"
        )
    cluster = _check_section(path, "cluster", data.get("cluster"), CLUSTER_KEYS[kind],
                             f" for cluster kind {kind!r}")
    prefect = _check_section(path, "prefect", data.get("prefect"), PREFECT_KEYS, "")
    _check_values(path, cluster, prefect)
    return Profile(str(path), cluster, prefect)


def _host_of(address: str) -> str:
    """The host of ``tcp://HOST``, ``HOST:PORT``, ``[V6]:PORT`` or ``:PORT`` ('' means every interface)."""
    address = address.split("://", 1)[-1]
    if address.startswith("["):
        return address[1:].split("]", 1)[0]
    if address.count(":") == 1:
        return address.split(":", 1)[0]
    return address


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # '' (every interface), 0.0.0.0 parses; a host name or interface IP may be public
        return False


def exposure_warnings(profile: Profile) -> list[str]:
    """One-line warnings for the sockets of ``profile``'s cluster that listen beyond this machine without TLS.

    A default profile binds everything to 127.0.0.1 and gets none. A ``local`` profile that sets
    ``cluster.host`` or ``cluster.dashboard_address`` off the loopback asked for it explicitly; it still gets
    a warning unless the Dask configuration sets up TLS (``distributed.comm.require-encryption`` or a
    ``tls://`` host for the scheduler and workers, ``distributed.scheduler.dashboard.tls.cert`` for the
    HTTP server), because the scheduler runs any code sent to it and its HTTP server serves metrics,
    worker addresses and logs, both without authentication. An ``address`` profile is warned for a
    ``tcp://`` scheduler on another host, a ``slurm``/``pbs`` one for an ``interface`` other than ``lo``,
    both unless ``cluster.security`` (TLS) is set (docs/clusters.md, "Security").
    """
    import dask

    spec, kind = profile.cluster, profile.kind
    comm_tls = "security" in spec or bool(dask.config.get("distributed.comm.require-encryption", False))
    if kind == "address":
        host = _host_of(spec["address"])
        if spec["address"].startswith("tcp://") and not _is_loopback(host) and not comm_tls:
            return [f"btf: warning: {profile.path}: the scheduler {spec['address']} (cluster.address) is reached "
                    "over the network without TLS: anyone who reaches it can run code on its workers and read "
                    "the data; use tls:// with cluster.security (docs/clusters.md, 'Security')"]
        return []
    if kind in ("slurm", "pbs"):
        warnings = []
        if spec.get("interface") != "lo" and not comm_tls:
            warnings.append(
                f"btf: warning: {profile.path}: the Dask scheduler and workers listen on interface "
                f"{spec.get('interface') or 'of the host name'} (cluster.interface) without TLS, so anyone on that "
                "network can run code on them; set cluster.security (docs/clusters.md, 'Security')")
        http = spec.get("dashboard_address", LOOPBACK)
        if not _is_loopback(_host_of(http)) and not dask.config.get("distributed.scheduler.dashboard.tls.cert", None):
            warnings.append(f"btf: warning: {profile.path}: the Dask scheduler's HTTP server listens on {http} "
                            "(cluster.dashboard_address) without TLS or authentication; use 127.0.0.1:8787 and "
                            "an SSH tunnel")
        return warnings
    if kind != "local":
        return []                   # kubernetes: a ClusterIP service, reachable inside the cluster only
    warnings = []
    host = spec.get("host", LOOPBACK)
    comm_tls = host.startswith("tls://") or comm_tls
    if not _is_loopback(_host_of(host)) and not comm_tls:
        warnings.append(
            f"btf: warning: {profile.path}: the Dask scheduler and workers listen on "
            f"{_host_of(host) or 'every interface'} (cluster.host) without TLS, so anyone who reaches this "
            f"machine can run code on them; use host {LOOPBACK} or set distributed.comm.require-encryption "
            "and distributed.comm.tls.* in the Dask config"
        )
    http = dashboard_address(spec)
    http_tls = bool(dask.config.get("distributed.scheduler.dashboard.tls.cert", None))
    if not _is_loopback(_host_of(http)) and not http_tls:
        warnings.append(
            f"btf: warning: {profile.path}: the Dask scheduler's HTTP server (dashboard, /metrics, worker "
            f"addresses and logs) listens on {http} without TLS or authentication; use "
            f"dashboard_address {LOOPBACK}:8787 or set distributed.scheduler.dashboard.tls.cert in the Dask config"
        )
    return warnings


def dashboard_address(spec: dict[str, Any]) -> str:
    """``host:port`` of the scheduler's HTTP server: the profile's, else the cluster host on 8787 (dashboard) or
    a random port (it always serves /metrics); never the empty host, which distributed binds to 0.0.0.0."""
    if "dashboard_address" in spec:
        return spec["dashboard_address"]
    host = _host_of(spec.get("host", LOOPBACK)) or LOOPBACK
    host = f"[{host}]" if ":" in host else host
    return f"{host}:{8787 if spec.get('dashboard', False) else 0}"
