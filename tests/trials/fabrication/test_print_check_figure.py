"""print_check.png names its rows and views (trials.fabrication.print_check.write_check)."""

import imageio.v3 as iio
import numpy as np

from trials.fabrication.print_check import RENDER_PX, ROW_LABELS, VIEWS_DEG, CheckResult, write_check


def test_the_print_check_figure_labels_its_rows_and_views_and_keeps_the_renders(tmp_path):
    rng = np.random.default_rng(0)
    renders = []
    for _ in range(3):
        a = rng.integers(0, 240, (RENDER_PX, RENDER_PX, 3), dtype=np.uint8)
        b = a + np.uint8(10)
        mask = np.zeros((RENDER_PX, RENDER_PX), bool)
        mask[64:192, 64:192] = True
        renders.append((a, b, mask))
    result = CheckResult([0.01, 0.02, 0.03], 0.01, {"side": 0.01}, 0, [], renders)
    paths = write_check(tmp_path, result)
    fig = iio.imread(paths["png"])[..., :3]
    label_px, bar_px, gap_px = 96, 18, 4
    assert fig.shape == (bar_px + 3 * RENDER_PX, label_px + 3 * RENDER_PX + 2 * gap_px, 3)
    for v, (a, b, mask) in enumerate(renders):
        x = label_px + v * (RENDER_PX + gap_px)
        col = fig[bar_px:, x : x + RENDER_PX]
        assert np.array_equal(col[:RENDER_PX], a) and np.array_equal(col[RENDER_PX : 2 * RENDER_PX], b)
        diff = col[2 * RENDER_PX :]
        assert np.all(diff[mask] == 40) and np.all(diff[~mask] == 0)  # |a - b| x 4 on the object only
        assert (fig[:bar_px, x : x + RENDER_PX] > 128).any()  # the view's caption, white on black
    labels = fig[:, :label_px].astype(int).sum(-1)
    for i in range(len(ROW_LABELS)):  # each row's name is written at its middle, nothing else there
        mid = bar_px + i * RENDER_PX + RENDER_PX // 2
        assert (labels[mid - 8 : mid + 8] < 300).any()
        assert (labels[bar_px + i * RENDER_PX : bar_px + i * RENDER_PX + 40] == 3 * 255).all()
    assert len(VIEWS_DEG) >= 3 and ROW_LABELS == ("optimised", "printed back", "|diff| x 4")
