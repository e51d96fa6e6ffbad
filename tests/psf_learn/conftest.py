"""Fixtures shared by the psf_learn tests: a CPU-only torch, image folders, a trained model."""

import numpy as np
import pytest

from doe.infra.cli import main


@pytest.fixture(scope="module")
def on_the_cpu():
    """Train on the CPU in a module's tests, GPU or not: only CPU runs repeat bit for bit.

    The tests of the CUDA path (``gpu``) put the GPU back; they run where there is one.
    """
    import torch

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch.cuda, "is_available", lambda: False)
        yield


@pytest.fixture(scope="session")
def image_folder():
    """Return make(path, n=2, size=40): a new folder of n dead-leaves PNGs, size x size."""
    from skimage import io

    from psf_learn.images import dead_leaves

    def make(path, n=2, size=40):
        path.mkdir()
        rng = np.random.default_rng(0)
        for i in range(n):
            img = (dead_leaves(size, rng, n_disks=100) * 255).astype(np.uint8)
            io.imsave(path / f"img{i}.png", img, check_contrast=False)
        return path

    return make


@pytest.fixture(scope="module")
def trained(request, tmp_path_factory, on_the_cpu, image_folder):
    """Return (model folder, image folder) of ``doefab learn`` with the module's ``SMALL`` flags.

    One tiny training per test module (``SMALL``: a few steps of a small network), on
    two 40 x 40 images.
    """
    root = tmp_path_factory.mktemp("learn")
    images = image_folder(root / "images")
    out = root / "model"
    small = request.module.SMALL
    assert main(["learn", "--out", str(out), "--images", str(images), *small]) == 0
    return out, images


@pytest.fixture
def fake_process_group(monkeypatch):
    """Return fake(rank, size): make torch.distributed report a process group.

    ``fake`` returns the list that the group's barrier and destroy calls are appended to.
    """
    import torch

    def fake(rank, size):
        calls = []
        dist = torch.distributed
        monkeypatch.setattr(dist, "is_initialized", lambda: True)
        monkeypatch.setattr(dist, "get_rank", lambda: rank)
        monkeypatch.setattr(dist, "get_world_size", lambda: size)
        monkeypatch.setattr(dist, "barrier", lambda: calls.append("barrier"))
        monkeypatch.setattr(dist, "destroy_process_group", lambda: calls.append("destroy"))
        return calls

    return fake


@pytest.fixture(scope="session")
def damaged_model():
    """Return damage(out, model, edit): a copy ``model`` of folder ``out``, model.pt edited.

    ``edit`` changes the model.pt record in place. The copy has no learn.json: its
    hashes would catch the edit first.
    """
    import shutil

    import torch

    def damage(out, model, edit):
        shutil.copytree(out, model)
        (model / "learn.json").unlink()
        record = torch.load(model / "model.pt", weights_only=True)
        edit(record)
        torch.save(record, model / "model.pt")
        return model

    return damage
