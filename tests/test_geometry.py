"""The BEV grid: sizes of the paper's settings and metre <-> pixel <-> normalised round trips."""

import numpy as np
import pytest
import torch

from instagram_hdmap.config import ConfigError, GridConfig
from instagram_hdmap.geometry import BEVGrid


def test_paper_sizes():
    g = BEVGrid.from_config(GridConfig())
    assert (g.H, g.W, g.Hc, g.Wc) == (200, 400, 25, 50)
    long = BEVGrid.from_config(GridConfig(xbound=(-50, 50), ybound=(-50, 50), resolution=0.25))
    assert (long.H, long.W) == (400, 400)
    coarse = BEVGrid.from_config(GridConfig(resolution=0.3, cell_size=4))
    assert (coarse.H, coarse.W, coarse.Hc, coarse.Wc) == (100, 200, 25, 50)


def test_official_export_mapping():
    # InstaGraM exports pixel coordinates as coord * 0.15 + (-29.925, -14.925).
    g = BEVGrid.from_config(GridConfig())
    px = np.array([[0.0, 0.0], [399.0, 199.0], [12.0, 7.0]])
    np.testing.assert_allclose(g.px_to_m(px), px * 0.15 + np.array([-29.925, -14.925]))


def test_round_trips_numpy_and_torch():
    g = BEVGrid.from_config(GridConfig())
    rng = np.random.default_rng(0)
    m = rng.uniform([-30, -15], [30, 15], size=(100, 2))
    np.testing.assert_allclose(g.px_to_m(g.m_to_px(m)), m, atol=1e-9)
    np.testing.assert_allclose(g.norm_to_m(g.m_to_norm(m)), m, atol=1e-9)
    t = torch.from_numpy(m).float()
    torch.testing.assert_close(g.px_to_m(g.m_to_px(t)), t)
    # corners of the grid map to -1 / +1 in normalised coordinates
    np.testing.assert_allclose(g.m_to_norm(np.array([[-30.0, -15.0], [30.0, 15.0]])), [[-1, -1], [1, 1]])


def test_pixel_index_matches_truncation_of_hdmapnet():
    g = BEVGrid.from_config(GridConfig())
    m = np.array([[-30.0, -15.0], [-29.851, -14.851], [29.99, 14.99]])
    idx = g.px_index(g.m_to_px(m))
    expected = np.floor((m - [-30, -15]) / 0.15).astype(int)
    np.testing.assert_array_equal(idx, expected)


def test_bad_grid_is_a_config_error():
    with pytest.raises(ConfigError, match="grid.cell_size"):
        BEVGrid.from_config(GridConfig(cell_size=7))
    with pytest.raises(ConfigError, match="grid.xbound"):
        BEVGrid.from_config(GridConfig(xbound=(-30, 30.1)))
