from os import PathLike
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

from . import sparse as sparse

__version__: str

StrPath = Union[str, "PathLike[str]"]
Calib = Union[StrPath, Mapping[str, npt.ArrayLike]]

class SparseOccError(Exception):
    """A bad file, dataset folder or run: the message names the file and the problem."""

class Model:
    """A trained network loaded from a training run folder (``sparseocc train --out RUN``)."""

    @staticmethod
    def load(run_dir: StrPath) -> "Model": ...
    def predict(
        self, image: npt.NDArray[np.uint8], calib: Calib, test_mirror: Optional[bool] = None
    ) -> npt.NDArray[np.uint8]:
        """Classes ``[X, Y, Z]`` from one RGB image ``[H, W, 3]`` and its KITTI calibration
        (a ``calib.txt`` path or ``{"P2": 3x4, "Tr": 3x4}``)."""
    def predict_frame(
        self, data_root: StrPath, sequence: str, frame: str, test_mirror: Optional[bool] = None
    ) -> npt.NDArray[np.uint8]:
        """Classes ``[X, Y, Z]`` of one dataset frame, in the run's data layout."""
    @property
    def grid_shape(self) -> Tuple[int, int, int]: ...
    @property
    def voxel_size_m(self) -> float: ...
    @property
    def origin_m(self) -> Tuple[float, float, float]: ...
    @property
    def kind(self) -> str: ...
    @property
    def class_names(self) -> List[str]: ...

def evaluate(
    gt_root: StrPath,
    pred_root: StrPath,
    dataset: str = "semantickitti",
    sequences: Union[None, str, Sequence[Union[str, int]]] = None,
    progress: bool = True,
) -> Dict[str, Any]: ...
def confusion(
    pred: npt.ArrayLike,
    gt: npt.ArrayLike,
    invalid: Optional[npt.ArrayLike] = None,
    *,
    visible: Optional[npt.ArrayLike] = None,
    dataset: str = "semantickitti",
) -> npt.NDArray[np.uint64]: ...
def report(
    confusion: npt.ArrayLike, dataset: str = "semantickitti", frames: int = 1
) -> Dict[str, Any]: ...
def class_names(dataset: str = "semantickitti") -> List[str]: ...
def synth(
    out: StrPath,
    preset: str = "kitti-small",
    sequences: Union[str, Mapping[str, int]] = "00:20,08:5",
    seed: int = 0,
    image_size: Optional[Tuple[int, int]] = None,
    progress: bool = True,
) -> Dict[str, Any]: ...
def read_voxels(
    path: StrPath, learning: bool = False
) -> Union[npt.NDArray[Any], Dict[str, npt.NDArray[np.uint8]]]: ...
def write_voxels(
    path: StrPath,
    data: Union[npt.ArrayLike, Mapping[str, npt.ArrayLike]],
    learning: bool = False,
) -> None: ...
def read_image(path: StrPath) -> npt.NDArray[np.uint8]: ...
