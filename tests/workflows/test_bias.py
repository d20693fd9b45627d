"""The resampling bias without the reference's noise: the estimator on synthetic data with a known bias and a known
reference noise, and the experiment's estimate at two reference sample counts."""

import pytest
import torch

from stereorepro.measure.anatomy import block_standard_error, reference_noise_mse, split_bias
from stereorepro.workflows.experiment import ExperimentConfig, run_experiment

PAPER = ("stereo", "temporal", "stereo_temporal")


def _blur(x: torch.Tensor) -> torch.Tensor:
    """A linear "scheme": the mean of each pixel and its right neighbour (the last column kept)."""
    y = x.clone()
    y[..., :-1] = 0.5 * (x[..., :-1] + x[..., 1:])
    return y


class TestSplitBiasOnSyntheticData:
    """A truth with edges, the blur as the scheme: its squared bias |blur(r) − r|² is known exactly, and so is the
    copy of the reference's noise the former estimator counts: (blur − I) e = (e_right − e) / 2 has variance σ²/2
    per value where a right neighbour exists."""

    H, W, SIGMA = 128, 160, 0.3  # σ of one sample

    def truth(self) -> torch.Tensor:
        g = torch.Generator().manual_seed(1)
        r = 0.3 * torch.rand(1, 3, self.H // 8, self.W // 8, generator=g, dtype=torch.float64)
        return torch.nn.functional.interpolate(r, size=(self.H, self.W), mode="nearest")  # 8×8 flat tiles

    def halves(self, spp_a: int, spp_b: int, seed: int):
        g = torch.Generator().manual_seed(seed)
        r = self.truth()
        a = r + self.SIGMA / spp_a**0.5 * torch.randn(r.shape, generator=g, dtype=torch.float64)
        b = r + self.SIGMA / spp_b**0.5 * torch.randn(r.shape, generator=g, dtype=torch.float64)
        return r, a, b

    def test_recovers_the_known_bias_and_noise(self):
        spp = 8  # per half: a 16-spp reference
        r, a, b = self.halves(spp, spp, seed=2)
        true_bias = float(((_blur(r) - r) ** 2).mean())
        products = split_bias(_blur(a) - a, _blur(b) - b)
        se = block_standard_error(products)
        assert abs(float(products.mean()) - true_bias) <= 4 * se, (float(products.mean()), true_bias, se)
        # the former estimator: the whole reference fed and scored against itself, bias + a noise copy
        whole = 0.5 * (a + b)
        old = float(((_blur(whole) - whole) ** 2).mean())
        noise_copy = self.SIGMA**2 / (2 * spp) / 2 * (self.W - 1) / self.W
        assert old == pytest.approx(true_bias + noise_copy, rel=0.03)
        assert noise_copy > 10 * se  # the copy the new estimate leaves out is far outside its error
        # the reference's own noise σ² / 16 from the halves' spread
        assert reference_noise_mse(a, b, spp, spp) == pytest.approx(self.SIGMA**2 / (2 * spp), rel=0.03)

    def test_unequal_halves(self):
        r, a, b = self.halves(4, 12, seed=3)
        true_bias = float(((_blur(r) - r) ** 2).mean())
        products = split_bias(_blur(a) - a, _blur(b) - b)
        assert abs(float(products.mean()) - true_bias) <= 4 * block_standard_error(products)
        assert reference_noise_mse(a, b, 4, 12) == pytest.approx(self.SIGMA**2 / 16, rel=0.03)

    def test_doubling_the_samples_leaves_it_unchanged(self):
        r = self.truth()
        est, old = {}, {}
        for spp in (8, 16):
            _, a, b = self.halves(spp, spp, seed=spp)
            p = split_bias(_blur(a) - a, _blur(b) - b)
            est[spp] = (float(p.mean()), block_standard_error(p))
            whole = 0.5 * (a + b)
            old[spp] = float(((_blur(whole) - whole) ** 2).mean())
        tol = 3 * (est[8][1] ** 2 + est[16][1] ** 2) ** 0.5
        assert abs(est[8][0] - est[16][0]) <= tol
        assert old[8] - old[16] > 5 * tol  # the former estimate halves its noise copy
        assert float(((_blur(r) - r) ** 2).mean()) > 0


#: Two runs that differ only in the reference's sample count (16 and 32 spp in 4-spp chunks: halves of 8 and 16
#: spp), 96×54, 6 frames: ~25 s on 2 cores.
DOUBLING = dict(
    scene="living_room",
    frames=6,
    width=96,
    height=54,
    ladder_spp=4,
    reference_chunk_spp=4,
    progress=False,
    alphas=(),
    flip=False,
    ssim=False,
)


@pytest.fixture(scope="module")
def doubled(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    runs = {}
    for spp in (16, 32):
        out = tmp_path_factory.mktemp(f"ref{spp}")
        cfg = ExperimentConfig(out=str(out), reference_spp=spp, cache_dir=str(cache), **DOUBLING)
        runs[spp] = run_experiment(cfg, log=lambda *a: None)["bias"]
    return runs


class TestDoublingTheReference:
    """Doubling the reference's samples must leave the bias estimate unchanged within its noise: the tolerance is
    twice the combined standard error of the two estimates, each the mean over the frames of the per-frame 8×8-tile
    standard error (an upper bound of the noise: the tiles' spread also holds the bias's own spatial variation,
    and averaging correlated frames is taken to shrink nothing). The former estimate (the whole reference fed and
    scored against itself) falls by its halved noise copy, beyond that tolerance for the stereo scheme, whose
    estimate has no history to make it noisy."""

    @staticmethod
    def tolerance(runs, k) -> float:
        return 2 * (runs[16][k]["bias_mse_se"]["avg"] ** 2 + runs[32][k]["bias_mse_se"]["avg"] ** 2) ** 0.5

    @pytest.mark.parametrize("k", PAPER)
    def test_bias_unchanged_within_noise(self, doubled, k):
        change = doubled[16][k]["bias_mse"]["avg"] - doubled[32][k]["bias_mse"]["avg"]
        assert abs(change) <= self.tolerance(doubled, k), (k, change, self.tolerance(doubled, k))

    @pytest.mark.parametrize("k", PAPER)
    def test_the_former_estimate_falls(self, doubled, k):
        old = {spp: doubled[spp][k]["rmse_noise_free"]["avg"] ** 2 for spp in (16, 32)}
        assert old[16] > old[32]  # its reference-noise copy halves
        if k == "stereo":
            assert old[16] - old[32] > self.tolerance(doubled, k)

    @pytest.mark.parametrize("k", PAPER)
    def test_shares_and_anatomy(self, doubled, k):
        b = doubled[32][k]
        assert b["bias_share"]["n"] == 6 and b["reference_noise_mse"]["avg"] > 0
        assert b["bias_share_without_reference_noise"]["avg"] >= b["bias_share"]["avg"]
        frames = 5 if k == "temporal" else 6  # the temporal step has no footprint at the first frame
        for field in ("pixels_pct", "mse_share_pct", "bias_share_pct"):
            total = sum(b["anatomy"][g][field]["avg"] for g in b["anatomy"])
            assert total == pytest.approx(100.0), (field, total)
            counts = {b["anatomy"][g][field]["n"] for g in b["anatomy"]}
            # a frame whose bias estimate is not positive (a bias within its noise of 0) has no bias shares
            assert counts == {frames} if field != "bias_share_pct" else len(counts) == 1 and counts <= set(range(1, 7))
