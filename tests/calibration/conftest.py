"""Shared synthetic data for the calibration tests (rendered once per session: GL renders cost time)."""

import numpy as np
import pytest

from calibration import synthetic as S
from calibration.intrinsics import BoardSpec, CameraIntrinsics

W, H = 640, 480
DIST = np.array([-0.08, 0.03, 0.0, 0.0, 0.0])


@pytest.fixture(scope="session")
def K():
    return S.default_K(W, H)


@pytest.fixture(scope="session")
def cam(K):
    return CameraIntrinsics(K, np.zeros(5), W, H)


@pytest.fixture(scope="session")
def board():
    return BoardSpec()


@pytest.fixture(scope="session")
def board_images(K, board):
    """(images, T_cam_board) of 12 distorted, blurred, noisy ChArUco views with known K and DIST."""
    from calibration.selfcheck import _board_views

    T = _board_views(board, 12, seed=3)
    cb = board.cv_board()
    imgs = [
        S.degrade(S.distort_image(S.render_planes([S.board_plane(cb, t)], K, W, H), K, DIST), 0.6, 2.0, seed=i)
        for i, t in enumerate(T)
    ]
    return imgs, T
