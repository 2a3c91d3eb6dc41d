"""A JSON document read with one-line errors naming the file (pipeline.core.io.read_json_object), and the
release's two documents that read through it (a bundle's bundle.json, a private half's answers.json)."""

from __future__ import annotations

import pytest

from skidbench.benchmark.release.bundle import BundleError, read_doc
from skidbench.benchmark.release.halves import read_answers
from skidbench.pipeline.core.errors import SkidbenchError
from skidbench.pipeline.core.io import read_json_object


def test_a_json_document_reads_back_and_each_fault_is_one_line_naming_the_file(tmp_path):
    good = tmp_path / "doc.json"
    good.write_text('{"format": "x", "n": 2}')
    assert read_json_object(good, SkidbenchError, "unused") == {"format": "x", "n": 2}
    with pytest.raises(SkidbenchError, match=r"nothing\.json: missing; no document here$"):
        read_json_object(tmp_path / "nothing.json", SkidbenchError, "no document here")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": \n')
    with pytest.raises(SkidbenchError) as info:
        read_json_object(bad, SkidbenchError, "unused")
    assert str(info.value).startswith(f"{bad}: not readable JSON (") and "\n" not in str(info.value)


def test_a_folder_without_its_document_is_not_a_bundle_nor_a_private_half(tmp_path):
    with pytest.raises(BundleError, match="bundle.json: missing; .* is not a skidbench bundle"):
        read_doc(tmp_path)
    with pytest.raises(BundleError, match="answers.json: missing; .* is not the private half"):
        read_answers(tmp_path, BundleError)
    (tmp_path / "bundle.json").write_text("[1, 2")
    with pytest.raises(BundleError, match="bundle.json: not readable JSON"):
        read_doc(tmp_path)
