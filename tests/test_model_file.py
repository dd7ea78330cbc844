"""The .nrt container: round trip, atomic writes, and one-line errors for bad files."""

import json
import struct

import pytest
import torch

from neuralrt.errors import ModelFileError
from neuralrt.io.model_file import FORMAT_VERSION, METADATA_KEY, header_digest, read_header, read_model_file, write_model_file


def _arrays():
    g = torch.Generator().manual_seed(1)
    return {
        "mlp.weight": torch.randn(16, 8, generator=g).half(),
        "table": torch.rand(2, 32, 3, generator=g),
        "bits": torch.randint(0, 255, (64,), dtype=torch.uint8, generator=g),
    }


@pytest.fixture
def model_path(tmp_path):
    path = tmp_path / "m.nrt"
    write_model_file(path, "lsnif", {"config": {"a": 1}, "bounds": [[0, 0, 0], [1, 2, 3]]}, _arrays())
    return path


def test_round_trip_bit_exact(model_path):
    f = read_model_file(model_path, method="lsnif")
    ref = _arrays()
    assert set(f.arrays) == set(ref)
    for k, v in ref.items():
        assert f.arrays[k].dtype == v.dtype and torch.equal(f.arrays[k], v)
    assert f.header["config"] == {"a": 1}
    assert f.header["format_version"] == FORMAT_VERSION and f.method == "lsnif"
    assert read_header(model_path)["bounds"] == [[0, 0, 0], [1, 2, 3]]


def test_atomic_write_leaves_no_temporaries(model_path):
    write_model_file(model_path, "lsnif", {}, _arrays())  # overwrite in place
    assert [p.name for p in model_path.parent.iterdir()] == ["m.nrt"]


def _error(path, method=None) -> str:
    with pytest.raises(ModelFileError) as info:
        read_model_file(path, method=method)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_missing_file(tmp_path):
    assert "not found" in _error(tmp_path / "nope.nrt")


@pytest.mark.parametrize("keep", [0, 5, 40, 0.5, -10])
def test_truncated_file(model_path, keep):
    data = model_path.read_bytes()
    n = keep if isinstance(keep, int) and keep >= 0 else (int(len(data) * keep) if keep > 0 else len(data) + keep)
    model_path.write_bytes(data[:n])
    assert "truncated" in _error(model_path)


def test_corrupted_array_data(model_path):
    data = bytearray(model_path.read_bytes())
    data[-3] ^= 0xFF  # a flipped byte inside the last array
    model_path.write_bytes(bytes(data))
    assert "corrupted" in _error(model_path)


def test_corrupted_header(model_path):
    data = bytearray(model_path.read_bytes())
    n = struct.unpack("<Q", data[:8])[0]
    header = data[8 : 8 + n].replace(b"format_version", b"format_versioX")
    model_path.write_bytes(bytes(data[:8] + header + data[8 + n :]))
    assert "corrupted" in _error(model_path)


def test_not_a_model_file(tmp_path):
    path = tmp_path / "junk.nrt"
    path.write_bytes(b"this is certainly not a model file at all" * 10)
    assert "not a neuralrt model file" in _error(path)


def test_newer_version_rejected(model_path):
    _rewrite_header(model_path, lambda h: h.update(format_version=FORMAT_VERSION + 1))
    msg = _error(model_path)
    assert "newer" in msg and str(FORMAT_VERSION + 1) in msg


def test_wrong_method_rejected(model_path):
    msg = _error(model_path, method="nbvh")
    assert "'lsnif' model" in msg and "'nbvh'" in msg


def _rewrite_header(path, change, sign: bool = True, text: str | None = None) -> None:
    """Edit the neuralrt header of a model file in place (keeps the arrays and their digest); with
    ``sign``, as a deliberate edit (the header's digest recomputed), else as corruption would;
    with ``text``, that JSON text in its place."""
    data = path.read_bytes()
    n = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8 : 8 + n])
    inner = json.loads(header["__metadata__"][METADATA_KEY])
    change(inner)
    if sign and inner.get("format_version", 0) >= 3:
        inner["header_sha256"] = header_digest(inner)
    elif sign:
        inner.pop("header_sha256", None)
    header["__metadata__"][METADATA_KEY] = json.dumps(inner) if text is None else text
    raw = json.dumps(header).encode()
    raw += b" " * ((8 - len(raw) % 8) % 8)
    path.write_bytes(struct.pack("<Q", len(raw)) + raw + data[8 + n :])


def test_the_same_model_writes_the_same_bytes(tmp_path):
    # The header's digest was a second metadata key, and safetensors writes its keys in no fixed order.
    written = set()
    for k in range(8):
        path = write_model_file(tmp_path / f"{k}.nrt", "lsnif", {"config": {"a": 1}, "bounds": [[0, 0, 0], [1, 2, 3]]}, _arrays())
        written.add(path.read_bytes())
    assert len(written) == 1


def test_a_changed_header_value_is_caught(model_path):
    # One digit of the bounds changed (as a flipped bit would): the JSON still parses and validates.
    _rewrite_header(model_path, lambda h: h["bounds"][1].__setitem__(0, h["bounds"][1][0] + 0.25), sign=False)
    assert "corrupted header (checksum mismatch)" in _error(model_path)


def test_a_header_claiming_an_older_version_is_still_checked(model_path):
    # format_version 3 -> 2 is one bit: a file with a digest is checked whatever version it claims.
    _rewrite_header(model_path, lambda h: h.update(format_version=2), sign=False)
    assert "checksum mismatch" in _error(model_path)


def test_a_current_file_without_its_header_digest_is_corrupted(model_path):
    data = model_path.read_bytes()
    model_path.write_bytes(data.replace(b"header_sha256", b"header_sha25X"))
    assert "missing 'header_sha256'" in _error(model_path)


@pytest.fixture(scope="module")
def lsnif_file(tmp_path_factory):
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel

    model = LSNIFModel.from_mesh(sphere(2), LSNIFConfig.preset("lq"))
    return model, model.save(tmp_path_factory.mktemp("m") / "ball.nrt")


def test_model_header_is_typed_and_stores_nothing_derivable(lsnif_file):
    from neuralrt.io.model_file import read_model_header

    model, path = lsnif_file
    raw = read_header(path)
    assert set(raw) == {"format_version", "method", "arrays_sha256", "header_sha256", "config", "bounds", "materials", "training",
                        "mesh_sha256", "mesh_name"}
    header = read_model_header(path)
    assert header.method == "lsnif" and header.config["method"] == "lsnif" and header.mesh_sha256 == model.mesh_hash
    assert header.materials[0].name == "default"


def test_version_1_files_still_load(lsnif_file, tmp_path):
    from neuralrt.methods import load_model
    from neuralrt.rays import Rays

    model, path = lsnif_file
    old = tmp_path / "v1.nrt"
    old.write_bytes(path.read_bytes())

    def as_version_1(h):  # what format 1 wrote: derivable box and memory, no method in the config
        h.update(format_version=1, box=h["bounds"], memory_bytes={"total": 1})
        del h["config"]["method"]

    _rewrite_header(old, as_version_1)
    loaded, current = load_model(old), load_model(path)
    o = torch.randn(64, 3, generator=torch.Generator().manual_seed(0)) * 3
    assert loaded.config == current.config and loaded.mesh_hash == model.mesh_hash
    assert torch.equal(loaded.intersect(Rays(o, -o)).t, current.intersect(Rays(o, -o)).t)


def test_version_2_files_load_without_a_header_digest(lsnif_file, tmp_path):
    from neuralrt.methods import load_model

    model, path = lsnif_file
    old = tmp_path / "v2.nrt"
    old.write_bytes(path.read_bytes())
    _rewrite_header(old, lambda h: h.update(format_version=2))  # what format 2 wrote: no header_sha256
    assert b"header_sha256" not in old.read_bytes()
    assert load_model(old).config == model.config


def test_invalid_model_header_is_one_line(lsnif_file, tmp_path):
    from neuralrt.methods import load_model

    _, path = lsnif_file
    bad = tmp_path / "bad.nrt"
    bad.write_bytes(path.read_bytes())
    _rewrite_header(bad, lambda h: h.update(bounds=[[0, 0], [1, 1, 1]]))
    with pytest.raises(ModelFileError, match=r"invalid model header \(bounds\.0"):
        load_model(bad)


@pytest.mark.parametrize(
    "bounds, message",
    [([[float("nan"), 0, 0], [1, 1, 1]], r"bounds\.0\.0: Input should be a finite number"),
     ([[0, 0, 0], [1, float("inf"), 1]], r"bounds\.1\.1: Input should be a finite number"),
     ([[0, 2, 0], [1, 1, 1]], r"lo \[0\.0, 2\.0, 0\.0\] is above hi"),
     ([[-1e300, 0, 0], [1e300, 1, 1]], r"lie beyond float32's range")],  # inf in float32: no hits at all
)
def test_non_finite_inverted_or_huge_bounds_are_refused(lsnif_file, tmp_path, bounds, message):
    # The header is not covered by the arrays' checksum: an edited header must still be checked.
    from neuralrt.methods import load_model

    _, path = lsnif_file
    bad = tmp_path / "bad.nrt"
    bad.write_bytes(path.read_bytes())
    _rewrite_header(bad, lambda h: h.update(bounds=bounds))
    with pytest.raises(ModelFileError, match=message):
        load_model(bad)


def test_invalid_config_in_header_names_the_key(lsnif_file, tmp_path):
    from neuralrt.methods import load_model

    _, path = lsnif_file
    bad = tmp_path / "bad.nrt"
    bad.write_bytes(path.read_bytes())
    _rewrite_header(bad, lambda h: h["config"]["inference"].update(occlusion_threshold=float("nan")))
    with pytest.raises(ModelFileError) as err:
        load_model(bad)
    message = str(err.value)
    assert "inference.occlusion_threshold: Input should be a finite number" in message
    assert "\n" not in message and "errors.pydantic.dev" not in message


def test_data_beyond_the_arrays_is_corruption_not_truncation(model_path):
    # safetensors reports both as "file not fully covered"; the sizes tell them apart
    model_path.write_bytes(model_path.read_bytes() + b"\0" * 24)
    with pytest.raises(ModelFileError, match=r"corrupted model file \(24 bytes after the arrays its header lists\)"):
        read_model_file(model_path)


def _rewrite_arrays(path, out, change) -> None:
    """A copy of model file ``path`` at ``out`` with its arrays edited by ``change`` (checksums recomputed:
    a file that is well formed, but wrong)."""
    f = read_model_file(path)
    header = {k: v for k, v in f.header.items() if k not in ("format_version", "method", "arrays_sha256")}
    arrays = dict(f.arrays)
    change(arrays)
    write_model_file(out, f.method, header, arrays)


@pytest.mark.parametrize("change, message", [
    (lambda a: a.__setitem__("encoder.table", a["encoder.table"].int()), r"array 'encoder\.table' is int32 .*, expected float16"),
    (lambda a: a["network.output.bias"].fill_(float("nan")), r"array 'network\.output\.bias' holds NaN or infinite values"),
    (lambda a: a.__setitem__("evil", torch.zeros(8)), r"arrays it does not use: evil"),
])
def test_well_formed_but_wrong_arrays_are_refused(lsnif_file, tmp_path, change, message):
    # They loaded, and answered garbage (an int32 table read as numbers) or NaN.
    from neuralrt.methods import load_model

    _, path = lsnif_file
    _rewrite_arrays(path, tmp_path / "bad.nrt", change)
    with pytest.raises(ModelFileError, match=r"invalid LSNIF model \(" + message):
        load_model(tmp_path / "bad.nrt")


@pytest.mark.parametrize("children, message", [
    ([[1_000_000_000, 1_000_000_001]], "child indices must be two adjacent nodes after their parent"),
    ([[0, 1]], "child indices must be two adjacent nodes after their parent"),  # a loop to itself
    ([[-5, -1]], r"leaf rows must be \(-1, -1\)"),
])
def test_an_nbvh_tree_the_traversal_cannot_walk_is_refused(tmp_path, children, message):
    # The kernels index by the child indices unchecked: 10^9 loaded, then crashed the process (SIGSEGV).
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods import load_model
    from neuralrt.methods.nbvh import NBVHModel
    from neuralrt.methods.nbvh_config import NBVHConfig

    path = NBVHModel.from_mesh(sphere(1), NBVHConfig.preset("cpu")).save(tmp_path / "ok.nrt")
    assert load_model(path).num_nodes >= 1
    _rewrite_arrays(path, tmp_path / "bad.nrt", lambda a: a.__setitem__("cut.children", torch.tensor(children, dtype=torch.int32)))
    with pytest.raises(ModelFileError, match=r"invalid N-BVH model \(ValueError: the tree's " + message):
        load_model(tmp_path / "bad.nrt")


@pytest.mark.parametrize("text, message", [
    ('{"format_version": 3, "method": "lsnif", "arrays_sha256": "", "deep": ' + "[" * 100_000 + "]" * 100_000 + "}",
     r"corrupted header \(JSON nested too deeply\)"),  # was a RecursionError traceback
    ('{"format_version": 3, "method": "lsnif", "arrays_sha256": "", "deep": ' + "[" * 500 + "]" * 500 + "}",
     r"corrupted header \(nested deeper than 32 levels\)"),  # (parsed, then `info` printing it overflowed)
    ('{"format_version": 3, "method": "lsnif", "arrays_sha256": "", "mesh_name": "\\ud800"}',
     r"corrupted header \(a string that is not valid Unicode text\)"),  # `info` failed printing it
    ('{"format_version": true, "method": "lsnif", "arrays_sha256": ""}', r"corrupted header \(format_version True\)"),
])
def test_headers_that_parse_oddly_are_one_line_errors(model_path, text, message):
    _rewrite_header(model_path, lambda h: None, text=text)
    with pytest.raises(ModelFileError, match=message):
        read_header(model_path)



@pytest.mark.parametrize("method, change, message", [
    # 40 levels of 2^24 rows of 16 features: 43 GB of table, asked for by a file of a few KB
    ("lsnif", lambda c: c["encoding"].update(resolutions=[64] * 40, log2_table_size=24, features_per_level=16),
     r"array 'encoder\.table' is \[2, 131072, 3\], expected \[40, 16777216, 16\] by its config"),
    ("lsnif", lambda c: c["network"].update(hidden_layers=16, hidden_width=4096), r"array 'network\.hidden\.0\.weight' is "),
    ("nbvh", lambda c: c["network"].update(hidden_layers=6), r"arrays missing: network\.hidden\.4\.weight"),
])
def test_a_config_asking_for_more_than_its_arrays_is_refused_before_allocating(tmp_path, method, change, message):
    # The model was built from the config before its arrays were compared: a 2 KB file took GBs.
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods import get_method, load_model

    spec = get_method(method)
    path = spec.model_class.from_mesh(sphere(1), spec.config_class.preset(spec.default_presets["*"])).save(tmp_path / "m.nrt")
    _rewrite_header(path, lambda h: change(h["config"]))
    with pytest.raises(ModelFileError, match=r"invalid (LSNIF|N-BVH) model \(" + message):
        load_model(path)


_TRUNCATE_WHILE_READING = """
import os, sys
from neuralrt.io import model_file
path = sys.argv[1]
parse = model_file._parse_header
def parse_then_truncate(p, handle):  # another process's `cp small.nrt model.nrt` truncates first
    header = parse(p, handle)
    os.truncate(path, 4096)
    return header
model_file._parse_header = parse_then_truncate
try:
    model_file.read_model_file(path)
except model_file.ModelFileError as exc:
    print(exc)
"""


def test_a_file_truncated_while_it_is_read_is_one_line(tmp_path):
    # Its arrays were read from safetensors' memory map: the truncated pages ended the process (SIGBUS).
    import subprocess
    import sys

    path = write_model_file(tmp_path / "m.nrt", "lsnif", {}, {"table": torch.zeros(1 << 18)})  # 1 MB past the first page
    size = path.stat().st_size
    run = subprocess.run([sys.executable, "-c", _TRUNCATE_WHILE_READING, str(path)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-500:]
    assert run.stdout.strip() == f"{path}: the model file changed while it was read ({size} bytes, then 4096)"
