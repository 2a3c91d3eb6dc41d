"""What made a result: the code and the environment, for every MLflow run and every fit's fingerprint.

- :func:`code_identity`: a model class's code, as its distribution (name, version), a digest of the source
  files it runs (:func:`code_digest`), and the installed versions of the distribution's declared
  requirements. The digest is what an editable install changes without a version bump: it is part of
  every fit's fingerprint (``models/fitting/fit.py`` ``fit_stamp``), so an edited model is refitted, and of
  its run's tags. A built-in model: its module and the skidbench modules it imports, transitively
  (pipeline/runner/code_closure.py), so an edit of one model refits that model and those built on it; a
  plugin: the files of its package and the skidbench modules they import.
- :func:`environment`: skidbench's version and git commit (``+dirty`` with local changes), the versions of
  Python and of the libraries the numbers depend on, the lock file (``requirements.lock``: its digest and
  whether the installed versions match it), the platform, the processor and the code paths the
  numerical libraries run on it (``pipeline/runner/cpu.py``), the thread settings.
- :func:`run_tags`, :func:`code_tags`: both as flat ``skidbench.*`` tags (strings); the benchmark logs them
  on each run. :func:`requirements_of`: the pip requirements of a logged MLflow Model.

Nothing here imports MLflow or a model; reading the facts costs milliseconds (the environment is read
once per process, a code digest each time it is asked: an edit between two fits of one process counts).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.metadata as md
import os
import platform
import re
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from skidbench.pipeline.runner import code_closure
from skidbench.pipeline.runner.cpu import code_paths, cpu_flags, cpu_model

#: the libraries whose versions a number depends on (their versions are recorded on every run)
LIBRARIES = (
    "numpy", "scipy", "numba", "llvmlite", "pandas", "pyarrow", "mlflow", "opencv-python-headless",
    "rosbags", "hydra-core", "threadpoolctl",
)  # fmt: skip
#: processor flags that pick the numerical libraries' code paths (recorded with the processor's model)
CPU_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512_vnni", "amx_tile")
#: thread settings read by NumPy's OpenBLAS, OpenMP, Numba and the stages
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
LOCK_FILE = "requirements.lock"
REPO = Path(__file__).resolve().parents[2]  # the source tree of an editable install


@functools.lru_cache(maxsize=None)
def version_of(dist: str) -> str | None:
    """The installed version of ``dist`` (None when it is not installed), read once per process: an
    evaluate asks for the same few hundred times (each run's provenance)."""
    try:
        return md.version(dist)
    except md.PackageNotFoundError:
        return None


def skidbench_version() -> str:
    return version_of("skidbench") or "unknown"


@functools.lru_cache(maxsize=1)
def git_commit() -> str:
    """The commit of the skidbench source tree ("+dirty" when tracked files have local changes), or
    "unknown" (an installed wheel, no git)."""
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# -- a model's code -----------------------------------------------------------------------------------
_content_memo: dict[str, tuple[tuple[int, int, int], str]] = {}


def _file_hash(path: Path) -> str:
    """BLAKE2b-128 of a file's content, memoised by (size, mtime, inode): an edit re-hashes it."""
    st = path.stat()
    key = (st.st_size, st.st_mtime_ns, st.st_ino)
    hit = _content_memo.get(str(path))
    if hit and hit[0] == key:
        return hit[1]
    h = hashlib.blake2b(path.read_bytes(), digest_size=16).hexdigest()
    _content_memo[str(path)] = (key, h)
    return h


def _skip(name: str) -> bool:
    return name.startswith(".") or name == "__pycache__" or name.endswith((".pyc", ".pyo", ".egg-info"))


def source_files(root: Path) -> list[Path]:
    """The files of a package folder (recursively; no bytecode, caches or hidden files), or the module
    file itself."""
    root = Path(root)
    if root.is_file():
        return [root]
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not _skip(d))
        out += [Path(dirpath, f) for f in sorted(filenames) if not _skip(f)]
    return out


def tree_digest(root: Path) -> tuple[str, int]:
    """(digest, number of files) of :func:`source_files` of ``root``: their paths relative to it and
    their contents. The same code installed in two places (an editable checkout, site-packages, another
    machine) has the same digest."""
    root = Path(root)
    base = root if root.is_dir() else root.parent
    h = hashlib.blake2b(digest_size=16)
    files = source_files(root)
    for f in files:
        h.update(f"{f.relative_to(base).as_posix()}\0{_file_hash(f)}\n".encode())
    return h.hexdigest(), len(files)


def package_root(module_name: str) -> Path | None:
    """The folder of the top-level package a module belongs to (the second level under a namespace
    package, e.g. ``skidbench.models``), or the module's own file when it is a top-level module."""
    parts = module_name.split(".")
    for depth in range(1, len(parts) + 1):
        name = ".".join(parts[:depth])
        try:
            mod = sys.modules.get(name) or importlib.import_module(name)
        except Exception:  # noqa: BLE001 - a module that cannot be imported has no files to digest
            return None
        file = getattr(mod, "__file__", None)
        if file is None:  # a namespace package: its own folders are shared; go one level down
            continue
        path = Path(file)
        return path.parent if path.name == "__init__.py" else path
    return None


def code_digest(module: str) -> tuple[str, int]:
    """(digest, number of files) of the code a model of ``module`` runs. A skidbench module: its file and
    those of the skidbench modules it imports, transitively (:func:`code_closure.closure`: the module's
    name and content of each, so the same code installed elsewhere has the same digest). Another module (a
    plugin, a test's class): the files of its top-level package (:func:`tree_digest`: any file of it may be
    what it runs) and the skidbench modules its Python files import. ``("?", 0)``: no files found."""
    if module.startswith(code_closure.PREFIX):
        own, n = "", 0
        files = code_closure.closure([module], _file_hash)
    else:
        root = package_root(module)
        if root is None:
            return "?", 0
        own, n = tree_digest(root)
        imported: set[str] = set()  # its relative imports are its own modules: only absolute ones matter
        for f in source_files(root):
            if f.suffix == ".py":
                imported |= code_closure.source_imports(f.read_text(errors="replace"), "")[0]
        files = code_closure.closure(imported, _file_hash)
    if not files:
        return (own, n) if own else ("?", 0)
    h = hashlib.blake2b(own.encode(), digest_size=16)
    for name in sorted(files):
        h.update(f"{name}\0{_file_hash(files[name])}\n".encode())
    return h.hexdigest(), n + len(files)


@functools.cache
def _top_level_distributions() -> dict[str, list[str]]:
    return md.packages_distributions()


def distribution_of(module_name: str) -> str | None:
    """The installed distribution that provides a module (None: not installed, e.g. a test's class)."""
    top = module_name.split(".")[0]
    if top == "skidbench":
        return "skidbench"
    dists = _top_level_distributions().get(top) or []
    return dists[0] if dists else None


_NAME = re.compile(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)")


@functools.cache
def requirement_versions(dist: str) -> dict[str, str]:
    """The installed version of each requirement the distribution declares, by name ("missing" when not
    installed). Requirements of extras (``; extra == ...``) are left out, and so is an uninstalled one
    under another marker (a platform or Python version it does not apply to). Read once per process."""
    out = {}
    for line in md.requires(dist) or []:
        spec, _, marker = line.partition(";")
        m = _NAME.match(spec)
        if not m or "extra" in marker:
            continue
        have = version_of(m.group(1))
        if have is None and marker.strip():
            continue
        out[m.group(1).lower().replace("_", "-")] = have or "missing"
    return dict(sorted(out.items()))


@dataclass(frozen=True)
class CodeIdentity:
    """A model's code: the distribution that installs it, its version, the digest of the files it runs
    (:func:`code_digest`) and the installed versions of the distribution's requirements."""

    module: str
    distribution: str  # "?" when the class comes from no installed distribution
    version: str
    digest: str
    files: int
    requires: dict[str, str] = field(default_factory=dict)

    def key(self) -> dict[str, str]:
        """What a fit's fingerprint holds (the requirements' versions are the environment's)."""
        return {"distribution": self.distribution, "version": self.version, "digest": self.digest}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def code_identity(cls: type, distribution: str | None = None, version: str | None = None) -> CodeIdentity:
    """The :class:`CodeIdentity` of a model class. ``distribution`` and ``version``: its entry point's
    distribution and its version when known (else looked up from the module)."""
    module = getattr(cls, "__module__", "?") or "?"
    dist = distribution if distribution not in (None, "", "?") else distribution_of(module)
    if version in (None, "", "?"):
        version = version_of(dist) if dist else None
    digest, n = code_digest(module)
    return CodeIdentity(
        module=module,
        distribution=dist or "?",
        version=version or "?",
        digest=digest,
        files=n,
        requires=dict(requirement_versions(dist)) if dist and version_of(dist) else {},
    )


def code_change(changed: dict[str, tuple[Any, Any]]) -> str | None:
    """``its code changed (digest <old> -> <new>)`` when the ``code`` entry of a fit's fingerprint changed
    (``Stamp.changed`` of pipeline/core/cache.py; :meth:`CodeIdentity.key`): an edited plugin, a release
    whose model code changed without a version bump; else None."""
    if "code" not in changed:
        return None
    then, now = ((c or {}) if isinstance(c, dict) else {} for c in changed["code"])
    if then.get("version") != now.get("version"):
        return f"its version changed ({then.get('version')} -> {now.get('version')})"
    return f"its code changed (digest {str(then.get('digest'))[:12]} -> {str(now.get('digest'))[:12]})"


def requirements_of(identity: CodeIdentity | None = None) -> list[str]:
    """pip requirements that load a logged model: skidbench and its requirements, MLflow, and the model's
    distribution and its requirements, each at its installed version (``name`` alone when unknown)."""
    pins: dict[str, str | None] = {"skidbench": version_of("skidbench"), "mlflow": version_of("mlflow")}
    for name, ver in requirement_versions("skidbench").items() if version_of("skidbench") else ():
        pins.setdefault(name, None if ver == "missing" else ver)
    if identity is not None and identity.distribution not in ("?", "skidbench"):
        pins[identity.distribution] = None if identity.version == "?" else identity.version
        for name, ver in identity.requires.items():
            pins.setdefault(name, None if ver == "missing" else ver)
    return [f"{n}=={v}" if v else n for n, v in pins.items()]


# -- the environment -------------------------------------------------------------------------------
def lock_status(lock: Path | None = None) -> str:
    """``<lock digest> match`` when every package the lock pins is installed at its version, else which
    differ; "no lock" when skidbench was not installed from its source tree (a wheel)."""
    lock = lock or REPO / LOCK_FILE
    if not lock.is_file():
        return "no lock (not installed from the source tree)"
    text = lock.read_text()
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    differ = []
    for line in text.splitlines():
        if line[:1].isalnum() and "==" in line:
            name, _, rest = line.partition("==")
            want = rest.split()[0].rstrip("\\").strip().split(";")[0]
            have = version_of(name.strip())
            if have != want:
                differ.append(f"{name.strip()} {have or 'missing'}!={want}")
    return f"{digest} match" if not differ else f"{digest} {len(differ)} differ: {', '.join(differ)}"


@functools.lru_cache(maxsize=1)
def _static_environment() -> dict[str, str]:
    flags = cpu_flags()
    env = {
        "skidbench": skidbench_version(),
        "git_commit": git_commit(),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        **{lib: version_of(lib) or "missing" for lib in LIBRARIES},
        "lock": lock_status(),
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "cpu_flags": " ".join(f for f in CPU_FLAGS if f in flags) or "unknown",
        "cpu_count": str(os.cpu_count()),
    }
    return env


def environment() -> dict[str, str]:
    """The environment of this process (see the module docstring), as strings."""
    env = dict(_static_environment())
    env["code_paths"] = " ".join(f"{k}={v}" for k, v in code_paths().items())
    env["threads"] = " ".join(f"{v}={os.environ[v]}" for v in THREAD_VARS if v in os.environ) or "default"
    return env


def run_tags() -> dict[str, str]:
    """:func:`environment` as run tags: ``skidbench.version``, ``skidbench.git_commit`` and
    ``skidbench.env.<name>`` for the rest."""
    env = environment()
    tags = {"skidbench.version": env.pop("skidbench"), "skidbench.git_commit": env.pop("git_commit")}
    tags.update({f"skidbench.env.{k}": v for k, v in env.items()})
    return tags


def code_tags(identity: CodeIdentity) -> dict[str, str]:
    """A model's :class:`CodeIdentity` as run tags ``skidbench.code.*``."""
    return {
        "skidbench.code.distribution": identity.distribution,
        "skidbench.code.version": identity.version,
        "skidbench.code.digest": identity.digest,
        "skidbench.code.files": str(identity.files),
        "skidbench.code.module": identity.module,
        "skidbench.code.requires": " ".join(f"{n}=={v}" for n, v in identity.requires.items()) or "-",
    }
