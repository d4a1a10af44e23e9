"""Every reader refuses what is not a regular file before opening it: a named pipe would
otherwise wait for a writer forever, a folder reads as a confusing error."""

import os
import sys

import pytest

from plenopiv.errors import PlenopivError


def readers():
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera, read_toml
    from plenopiv.config.experiment import load_experiment
    from plenopiv.products.images import read_frames, read_image
    from plenopiv.products.vectors import load_vectors
    from plenopiv.products.volume import load_volume
    from plenopiv.workflow.masks import read_mask

    return {"image": read_image, "frames": read_frames, "volume": load_volume,
            "vectors": load_vectors, "calibration": Calibration.load,
            "mask": read_mask, "camera": load_camera, "toml": read_toml,
            "experiment": load_experiment}


SUFFIX = {"image": ".tif", "frames": ".tif", "volume": ".h5", "vectors": ".h5",
          "calibration": ".h5", "mask": ".npy", "camera": ".toml", "toml": ".toml",
          "experiment": ".toml"}


@pytest.mark.skipif(sys.platform == "win32", reason="no named pipes as files")
@pytest.mark.timeout(30)
@pytest.mark.parametrize("kind", sorted(SUFFIX))
def test_a_named_pipe_is_refused_not_read(tmp_path, kind):
    fifo = tmp_path / f"pipe{SUFFIX[kind]}"
    os.mkfifo(fifo)
    with pytest.raises(PlenopivError, match="not a regular file"):
        readers()[kind](fifo)


@pytest.mark.parametrize("kind", sorted(SUFFIX))
def test_a_folder_is_refused_by_name(tmp_path, kind):
    folder = tmp_path / f"folder{SUFFIX[kind]}"
    folder.mkdir()
    with pytest.raises(PlenopivError, match="folder"):
        readers()[kind](folder)
