from typing import Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

Triple = Union[int, Sequence[int]]

def conv3d(
    coords: npt.ArrayLike,
    feats: npt.ArrayLike,
    weight: npt.ArrayLike,
    spatial_shape: Triple,
    kernel: Triple,
    stride: Triple = 1,
    padding: Triple = 0,
    dilation: Triple = 1,
    subm: bool = False,
    transposed: bool = False,
    batch_size: Optional[int] = None,
) -> Tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]: ...
