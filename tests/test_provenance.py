"""Provenance and reproducibility: the processor code paths pinned before NumPy loads, a model's code
identity (its package's files, wherever installed), the lock file's check, the pip requirements of a logged
model and the tags every run carries."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from skidbench.pipeline.runner import cpu, environment

REPO = Path(__file__).resolve().parents[1]
V3 = frozenset({"sse4_2", "avx", "avx2", "fma", "f16c", "bmi1", "bmi2"})
AVX512 = V3 | {"avx512f", "avx512cd", "avx512bw", "avx512dq", "avx512vl", "avx512_vnni"}


def test_pins_cap_every_library_at_avx2_on_an_avx512_processor_and_touch_nothing_without_avx2():
    p = cpu.pins(AVX512)
    assert p["OPENBLAS_CORETYPE"] == "Haswell"
    assert "X86_V4" in p["NPY_DISABLE_CPU_FEATURES"] or "AVX512_SKX" in p["NPY_DISABLE_CPU_FEATURES"]
    # only the AVX-512 targets this processor has (OpenCV prints a line for any other)
    assert p["OPENCV_CPU_DISABLE"].split(",") == ["AVX512F", "AVX512-COMMON", "AVX512-SKX", "AVX512-CLX"]
    assert cpu.pins(V3) == {"OPENBLAS_CORETYPE": "Haswell"}  # AVX2 is already the top: only OpenBLAS
    assert cpu.pins(V3 - {"avx2"}) == {} and cpu.pins(frozenset()) == {}


def test_pin_keeps_what_the_user_set_and_native_cpu_turns_it_off(monkeypatch):
    monkeypatch.setattr(cpu, "pins", lambda flags=None: {"OPENBLAS_CORETYPE": "Haswell", "X_PIN": "1"})
    monkeypatch.setenv("OPENBLAS_CORETYPE", "SkylakeX")
    monkeypatch.delenv("X_PIN", raising=False)
    monkeypatch.delenv(cpu.NATIVE_ENV, raising=False)
    assert cpu.pin() == {"X_PIN": "1"} and os.environ["OPENBLAS_CORETYPE"] == "SkylakeX"
    monkeypatch.delenv("X_PIN")
    monkeypatch.setenv(cpu.NATIVE_ENV, "1")
    assert cpu.pin() == {} and "X_PIN" not in os.environ


def _fresh_python(code: str, **env: str) -> str:
    e = {k: v for k, v in os.environ.items() if k not in cpu.pins() and k != cpu.NATIVE_ENV}
    cmd = [sys.executable, "-c", code]
    done = subprocess.run(cmd, env={**e, **env}, capture_output=True, text=True, timeout=120, check=True)
    return done.stdout


def test_importing_any_skidbench_subpackage_pins_before_numpy_loads_in_a_fresh_process():
    if not cpu.pins():
        pytest.skip("this processor has no x86-64-v3 level to pin to")
    code = (
        "import os, sys\nimport skidbench.models.base\n"
        "from skidbench.pipeline.runner.cpu import code_paths, pins\n"
        "print(all(os.environ.get(k) == v for k, v in pins().items()), code_paths()['openblas'])"
    )
    ok, blas = _fresh_python(code).split(maxsplit=1)
    assert ok == "True" and blas.startswith("Haswell")  # OpenBLAS runs the pinned kernels, whatever it found
    native = _fresh_python(code, SKIDBENCH_NATIVE_CPU="1")
    assert native.split()[0] == "False"


def test_a_package_has_one_digest_wherever_it_is_installed_and_an_edit_changes_it(tmp_path):
    for where in ("a", "b"):
        pkg = tmp_path / where / "plug"
        (pkg / "sub").mkdir(parents=True)
        (pkg / "__init__.py").write_text("")
        (pkg / "model.py").write_text("K = 1\n")
        (pkg / "sub" / "data.yaml").write_text("x: 1\n")
        (pkg / "__pycache__").mkdir()
        (pkg / "__pycache__" / "model.cpython-311.pyc").write_bytes(os.urandom(16))  # never counted
    a, b = tmp_path / "a" / "plug", tmp_path / "b" / "plug"
    assert environment.tree_digest(a) == environment.tree_digest(b)
    assert environment.tree_digest(a)[1] == 3
    (b / "model.py").write_text("K = 2\n")  # same size, same name: content counts
    assert environment.tree_digest(a)[0] != environment.tree_digest(b)[0]
    (b / "model.py").write_text("K = 1\n")
    (b / "sub" / "data.yaml").rename(b / "sub" / "other.yaml")  # a renamed file counts too
    assert environment.tree_digest(a)[0] != environment.tree_digest(b)[0]


def test_a_builtin_models_code_is_the_files_it_imports_and_enters_its_requirements():
    from skidbench.models.kinematic.linear import ExtendedDifferentialDrive
    from skidbench.pipeline.runner import code_closure

    ident = environment.code_identity(ExtendedDifferentialDrive, "skidbench")
    assert ident.distribution == "skidbench" and ident.version == environment.version_of("skidbench")
    files = code_closure.closure([ExtendedDifferentialDrive.__module__], environment._file_hash)
    assert ident.files == len(files) and REPO / "models" / "base.py" in files.values()
    assert REPO / "models" / "__init__.py" in files.values()  # the packages above it run on import
    assert not any("friction" in str(f) or "ideal" in str(f) for f in files.values())
    assert ident.requires["numpy"] == environment.version_of("numpy")  # skidbench's own requirements
    reqs = environment.requirements_of(ident)
    assert reqs[:2] == [f"skidbench=={ident.version}", f"mlflow=={environment.version_of('mlflow')}"]
    assert f"scipy=={environment.version_of('scipy')}" in reqs


def test_a_plugins_requirements_name_its_distribution_and_its_libraries():
    ident = environment.CodeIdentity(
        "ridge.model", "skidbench-ridge", "0.3", "d" * 32, 2, {"scikit-learn": "1.7.2", "numpy": "2.4.6"}
    )
    reqs = environment.requirements_of(ident)
    assert "skidbench-ridge==0.3" in reqs and "scikit-learn==1.7.2" in reqs
    assert sum(r.startswith("numpy") for r in reqs) == 1  # one pin per library
    tags = environment.code_tags(ident)
    assert tags["skidbench.code.digest"] == "d" * 32
    assert tags["skidbench.code.requires"] == "scikit-learn==1.7.2 numpy==2.4.6"


def test_the_lock_check_names_each_installed_version_that_differs(tmp_path):
    np_version = environment.version_of("numpy")
    lock = tmp_path / "requirements.lock"
    lock.write_text(f"# header\nnumpy=={np_version} \\\n    --hash=sha256:00\n    # via skidbench\n")
    assert environment.lock_status(lock).endswith(" match")
    lock.write_text("numpy==0.0.1 \\\n    --hash=sha256:00\nno-such-dist-xyz==1.0\n")
    status = environment.lock_status(lock)
    assert f"numpy {np_version}!=0.0.1" in status and "no-such-dist-xyz missing!=1.0" in status
    assert "no lock" in environment.lock_status(tmp_path / "absent.lock")


def test_the_repositorys_lock_pins_what_this_environment_runs():
    """`make setup` installs requirements.lock: an environment it made matches it (a failure here means the
    lock and pyproject.toml drifted apart, or the environment was changed by hand: `make setup`)."""
    status = environment.lock_status()
    if status.startswith("no lock"):
        pytest.skip("skidbench is not installed from its source tree")
    assert status.endswith(" match"), status


def test_run_tags_carry_version_commit_libraries_platform_and_code_paths():
    tags = environment.run_tags()
    assert tags["skidbench.version"] == environment.version_of("skidbench")
    assert tags["skidbench.git_commit"] == environment.git_commit()
    for lib in ("numpy", "scipy", "numba", "pandas", "pyarrow", "mlflow"):
        assert tags[f"skidbench.env.{lib}"] == environment.version_of(lib)
    assert tags["skidbench.env.python"].endswith(".".join(map(str, sys.version_info[:3])))
    assert "openblas=" in tags["skidbench.env.code_paths"]
    assert all(isinstance(v, str) and v for v in tags.values())
    json.dumps(tags)
