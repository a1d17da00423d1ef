"""splats.bin: the stored 2D splats are exactly the bytes the budget paid for and redraw the image."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from splatk.errors import InputError
from splatk.image.file import HEADER_BYTES, encode_splats2d, load_splats2d, save_splats2d
from splatk.image.fit import ImageFitConfig, fit_image
from tests.scenes import synthetic_photo as _synthetic


CASES = [("gaussian", 0), ("gabor", 0), ("gabsplat", 0), ("learned", 0), ("learned", 8), ("learned-paper", 0)]


@pytest.mark.parametrize("kernel,shapes", CASES)
def test_file_is_the_paid_bytes_and_redraws_the_same_image(tmp_path, kernel, shapes):
    torch.set_num_threads(1)
    # enough iterations that the palette is made (at half the run) and trained
    model, _ = fit_image(_synthetic(), ImageFitConfig(kernel=kernel, budget_bytes=2500, iters=6, shapes=shapes,
                                                      backend="torch"))
    path = save_splats2d(model, tmp_path / "splats.bin")
    assert path.stat().st_size == HEADER_BYTES + model.describe_bytes()["bytes"]
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # an ordinary file, not mkstemp's 0600
    back = load_splats2d(path)
    assert (back.kernel, back.n, back.height, back.width) == (model.kernel, model.n, model.height, model.width)
    back.backend = "torch"
    with torch.no_grad():
        torch.testing.assert_close(back.render(), model.render(), atol=0, rtol=0)
    # and it writes the same bytes again
    assert encode_splats2d(back) == path.read_bytes()


def test_unrounded_decoder_is_refused():
    from splatk.image.model import Splats2D

    m = Splats2D("learned", 4, 8, 8, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        m.decoder.l1.weight.add_(1e-4 * torch.arange(m.decoder.l1.weight.numel()).reshape(m.decoder.l1.weight.shape))
    with pytest.raises(ValueError, match="round_shared"):
        encode_splats2d(m)
    m.round_shared()
    assert len(encode_splats2d(m)) == HEADER_BYTES + m.describe_bytes()["bytes"]


def test_bad_files_name_the_file(tmp_path):
    model, _ = fit_image(_synthetic(), ImageFitConfig(kernel="learned", budget_bytes=2500, iters=2, shapes=8))
    data = encode_splats2d(model)
    cases = {"truncated": data[:-3], "trailing": data + b"\0", "magic": b"XXXXXX" + data[6:],
             "empty": b"", "version": data[:6] + bytes([9]) + data[7:]}
    for name, blob in cases.items():
        p = tmp_path / f"{name}.bin"
        p.write_bytes(blob)
        with pytest.raises(InputError) as err:
            load_splats2d(p)
        assert str(p) in str(err.value), name
    with pytest.raises(InputError, match="not found"):
        load_splats2d(tmp_path / "missing.bin")


def test_cli_image_writes_splats_and_image_decode_redraws_them(tmp_path):
    from PIL import Image
    from splatk_cli.main import cli

    photo = tmp_path / "p.png"
    Image.fromarray((_synthetic(32, 48).numpy() * 255).astype(np.uint8)).save(photo)
    out = tmp_path / "run"
    res = CliRunner().invoke(cli, ["image", str(photo), "--budget-bytes", "2000", "--out", str(out), "--iters", "6",
                                   "--downscale", "2", "--threads", "1", "-q", "--no-lpips"])
    assert res.exit_code == 0, res.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["file"] == "splats.bin" and m["file_bytes"] == (out / "splats.bin").stat().st_size
    assert m["file_bytes"] == m["bytes"] + HEADER_BYTES and m["bytes"] <= 2000
    png = tmp_path / "decoded.png"
    res = CliRunner().invoke(cli, ["image-decode", str(out / "splats.bin"), "--out", str(png)])
    assert res.exit_code == 0, res.output
    a = np.asarray(Image.open(png), dtype=np.int16)
    b = np.asarray(Image.open(out / "render.png"), dtype=np.int16)
    assert a.shape == b.shape and int(np.abs(a - b).max()) <= 1  # the same render, up to a rounding step
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"nope")
    res = CliRunner().invoke(cli, ["image-decode", str(bad), "--out", str(png)])
    assert res.exit_code == 2 and "bad.bin" in res.output and "Traceback" not in res.output
