"""The inference renderer: equal to a plain render of the same rays (no pruning, one chunk) and
to the two-pass pruned render (density pass, then the whole field on the kept samples), which it
replaces by one encoding of each marched sample; independent of the chunk size; lenses,
appearance codes, input checks, and training after a render."""

import copy

import pytest
import torch

from ngp_warp.data.cameras import generate_rays
from ngp_warp.training.config import TrainConfig
from ngp_warp.data.loading import load_scene
from ngp_warp.ops.field import FieldConfig, NGPField
from ngp_warp.training.model import RadianceModel
from ngp_warp.ops.prune import prune_samples
from ngp_warp.ops.raymarch import ray_marching
from ngp_warp.outputs.renderer import ChunkSizer, _marched_rows, auto_first_round, render_view
from ngp_warp.data.scene import write_demo_scene
from ngp_warp.training.trainer import Trainer

W, H = 20, 16


@pytest.fixture(scope="module")
def trainer(tmp_path_factory):
    path = write_demo_scene(tmp_path_factory.mktemp("renderer") / "demo", width=24, height=24, n_train=12,
                            n_test=1, supersample=1)
    config = TrainConfig(steps=60, target_samples=1 << 12, grid_resolution=32, steps_per_diagonal=256,
                         field=FieldConfig(n_levels=8, log2_hashmap_size=14, finest_resolution=128.0, hidden=32))
    t = Trainer(load_scene(path), config, device="cpu")
    t.train(show_progress=False)
    return t


def camera(trainer):
    split = trainer.scene.test
    intr = split.intrinsics[0] * torch.tensor([W / split.width, H / split.height, W / split.width, H / split.height])
    return split.c2w[0], intr


def plain_render(model, rays_o, rays_d, background: float) -> dict:
    """Every marched sample through the whole field, no pruning, one call."""
    with torch.no_grad():
        return model.render(rays_o, rays_d, model.field, background=torch.full((3,), background))


def pruned_render(model, rays_o, rays_d, background: float) -> dict:
    """The previous inference path: a density pass prunes, then the whole field (its hash grid
    and density MLP again) on the kept samples."""
    with torch.no_grad():
        return model.render(rays_o, rays_d, model.field, background=torch.full((3,), background),
                            sigma_fn=model.field.density)


def pixel_rays(c2w, intr, distortion=None, fisheye=False):
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    n = W * H
    dist = None if distortion is None else distortion.expand(n, 6)
    return generate_rays(c2w.expand(n, 3, 4), intr.expand(n, 4), dist, xs.reshape(-1).float(),
                         ys.reshape(-1).float(), fisheye=fisheye)


def assert_same_image(out, want):
    torch.testing.assert_close(out["rgb"].reshape(-1, 3), want["rgb"].clamp(0, 1), rtol=0, atol=2e-5)
    torch.testing.assert_close(out["opacity"].reshape(-1), want["opacity"], rtol=0, atol=2e-5)
    torch.testing.assert_close(out["depth"].reshape(-1), want["depth"], rtol=1e-5, atol=1e-4)


def denser_field(field, bump: float):
    """A copy of ``field`` whose log-density grows by ``bump`` × the sum of its last hidden
    activations (≥ 0)."""
    dense = copy.deepcopy(field)
    with torch.no_grad():
        dense.density_mlp[-1].weight[0] += bump
    return dense


@pytest.mark.parametrize("first_round", [None, 4, 16])
@pytest.mark.parametrize("bump", [0.0, 2.5, 5.0])  # trained; partly opaque; opaque within 4 samples
def test_render_view_equals_a_plain_render_and_shades_fewer_samples(trainer, bump, first_round):
    c2w, intr = camera(trainer)
    model = RadianceModel(denser_field(trainer.field, bump), trainer.grid, trainer.model.march)
    out = render_view(model, c2w, intr, W, H, background=0.25, first_round=first_round)
    rays = pixel_rays(c2w, intr)
    want = plain_render(model, *rays, 0.25)
    assert float(want["opacity"].max()) > 0.5  # not an empty view
    assert_same_image(out, want)
    two_pass = pruned_render(model, *rays, 0.25)
    assert_same_image(out, two_pass)
    assert out["n_marched"] == want["n_samples"] == two_pass["n_marched"]
    assert out["n_shaded"] == two_pass["n_samples"]
    assert 0 < out["n_shaded"] <= out["n_encoded"] <= out["n_marched"]
    assert first_round is not None or out["n_encoded"] == out["n_marched"]
    if bump == 5.0:  # opaque rays end early: their samples behind it skip the colour pass (after 60
        assert out["n_shaded"] < 0.8 * out["n_marched"]  # steps hardly any ray is that opaque)
        # ... and with rounds the density pass: every ray ends within its first round
        assert first_round is None or out["n_encoded"] == first_round * W * H
    if bump == 2.5 and first_round == 16:  # some rays end within 16 samples, the others go on
        assert first_round * W * H < out["n_encoded"] < 0.5 * out["n_marched"]


@pytest.mark.parametrize("chunk", [1, 37, 4096])
def test_chunks_do_not_change_the_image(trainer, chunk):
    c2w, intr = camera(trainer)
    whole = render_view(trainer.model, c2w, intr, W, H)
    chunked = render_view(trainer.model, c2w, intr, W, H, chunk=chunk)
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(chunked[key], whole[key], rtol=0, atol=1e-6)


@pytest.mark.parametrize("chunk", [None, 4096])
def test_a_chunk_that_marches_too_many_samples_is_rendered_in_halves(trainer, monkeypatch, chunk):
    """A barely trained field marches far more samples per ray than the chunk size guessed (a
    2 s lego run: 166M samples in one chunk, past one hash-grid call): with a sample budget of
    64, every chunk of more than a few rays is marched again as halves, and the image is the same."""
    import ngp_warp.outputs.renderer as renderer

    c2w, intr = camera(trainer)
    model = trainer.model
    model.view_samples_per_ray = None
    whole = render_view(model, c2w, intr, W, H, first_round=None)
    assert whole["n_marched"] > 8 * renderer.MAX_MARCHED_SHARE * 64  # the budget below splits it
    marched = []
    real_march = renderer.ray_marching

    def counting_march(*args, **kwargs):
        samples = real_march(*args, **kwargs)
        marched.append((args[0].shape[0], samples.n_samples))
        return samples

    monkeypatch.setattr(renderer, "sample_budget", lambda device: 64)
    monkeypatch.setattr(renderer, "ray_marching", counting_march)
    split = render_view(model, c2w, intr, W, H, chunk=chunk, first_round=None)
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(split[key], whole[key], rtol=0, atol=1e-6)
    assert split["n_marched"] == whole["n_marched"] and split["n_shaded"] == whole["n_shaded"]
    cap = renderer.MAX_MARCHED_SHARE * 64
    kept = [n for rays, n in marched if rays == 1 or n <= cap]
    assert marched[0][0] == W * H and len(kept) < len(marched)  # the first chunk was too large
    assert sum(kept) == whole["n_marched"]  # the chunks rendered cover every ray once
    assert all(n == cap + 1 for rays, n in marched if rays > 1 and n > cap)  # a dropped march stops counting


@pytest.mark.parametrize("fisheye", [False, True])
def test_lenses_render_their_own_rays(trainer, fisheye):
    c2w, intr = camera(trainer)
    distortion = torch.tensor([0.05, -0.02, 0.01, 0.004, 0.0, 0.0] if fisheye else [-0.1, 0.02, 0.0, 0.0, 1e-3, -2e-3])
    out = render_view(trainer.model, c2w, intr, W, H, distortion=distortion, fisheye=fisheye, background=0.5)
    assert_same_image(out, plain_render(trainer.model, *pixel_rays(c2w, intr, distortion, fisheye), 0.5))
    pinhole = render_view(trainer.model, c2w, intr, W, H, background=0.5)
    assert (out["rgb"] - pinhole["rgb"]).abs().max() > 1e-3  # the lens changed the picture (well past the tolerance)


def test_trainer_renders_distorted_test_views(trainer):
    split = trainer.scene.test
    out = trainer.render_image(split.c2w[0], split.intrinsics[0], 8, 6, distortion=torch.zeros(6), fisheye=True)
    assert out["rgb"].shape == (6, 8, 3)


def test_training_goes_on_after_a_render(trainer):
    c2w, intr = camera(trainer)
    render_view(trainer.model, c2w, intr, W, H)
    before = trainer.field.encoding.params.detach().clone()
    trainer.step()
    trainer.flush()
    assert not torch.equal(before, trainer.field.encoding.params.detach())
    assert trainer.field.training


@pytest.mark.parametrize("kwargs, message", [
    (dict(width=0), "width"), (dict(spp=0), "spp"), (dict(chunk=0), "chunk"),
    (dict(first_round=0), "first_round"), (dict(first_round="fast"), "first_round"),
    (dict(first_round=True), "first_round"),
    (dict(distortion=torch.zeros(4)), "k1 k2 k3 k4"), (dict(fisheye=True), "fisheye"),
])
def test_bad_arguments_are_refused(trainer, kwargs, message):
    c2w, intr = camera(trainer)
    args = dict(width=W, height=H) | kwargs
    with pytest.raises(ValueError, match=message):
        render_view(trainer.model, c2w, intr, args.pop("width"), args.pop("height"), **args)


def test_an_eps_that_is_zero_in_float32_encodes_every_sample(trainer):
    c2w, intr = camera(trainer)  # prune compares float32(eps) = 0: every sample composites
    model = RadianceModel(denser_field(trainer.field, 5.0), trainer.grid, trainer.model.march, early_stop_eps=1e-46)
    out = render_view(model, c2w, intr, W, H, background=0.25, first_round=4)
    assert out["n_encoded"] == out["n_shaded"] == out["n_marched"]
    assert_same_image(out, plain_render(model, *pixel_rays(c2w, intr), 0.25))


def test_auto_first_round_follows_the_last_views_shaded_samples(trainer):
    assert [auto_first_round(v) for v in (None, 0.0, 5.2, 10.7, 11.0, 20.1, 100.0)] == [16, 16, 16, 24, 24, 32, 152]
    c2w, intr = camera(trainer)
    model = RadianceModel(denser_field(trainer.field, 2.0), trainer.grid, trainer.model.march)
    first = render_view(model, c2w, intr, W, H)  # 16: no view yet
    assert model.view_shaded_per_ray == first["n_shaded"] / (W * H) > 12
    second = render_view(model, c2w, intr, W, H)  # more than 16 after the first
    assert auto_first_round(model.view_shaded_per_ray) > 16
    assert first["n_encoded"] != second["n_encoded"]  # the rounds changed, the image did not
    for key in ("rgb", "opacity", "depth"):
        torch.testing.assert_close(second[key], first[key], rtol=0, atol=1e-6)


def test_chunk_sizer_follows_the_densest_chunk():
    sizer = ChunkSizer(1 << 24, first_guess=64.0)
    assert sizer.next_size(10**9) == (1 << 24) // 64
    sizer.observe(1000, 8000)  # 8 samples per ray: below the guess, the guess stays
    assert sizer.next_size(10**9) == (1 << 24) // 64
    sizer.observe(1000, 256_000)
    assert sizer.next_size(10**9) == int((1 << 24) / (1.5 * 256))
    sizer.observe(10, 10**9)
    assert sizer.next_size(10**9) == 1 << 12
    assert sizer.next_size(5120) == 5120 and sizer.next_size(5121) == 4096  # a quarter more, not a tail chunk


def test_the_next_view_starts_from_the_last_views_samples_per_ray(trainer, monkeypatch):
    c2w, intr = camera(trainer)
    model = trainer.model
    model.view_samples_per_ray = None
    first = render_view(model, c2w, intr, W, H)
    seen = model.view_samples_per_ray
    assert seen is not None and seen >= first["n_marched"] / (W * H) > 0  # the densest chunk's count
    guesses = []
    real = ChunkSizer.__init__

    def spy(self, budget, first_guess=64.0):
        guesses.append(first_guess)
        real(self, budget, first_guess)

    monkeypatch.setattr(ChunkSizer, "__init__", spy)
    second = render_view(model, c2w, intr, W, H)
    assert guesses == [1.5 * seen]
    for key in ("rgb", "opacity", "depth"):  # chunking does not change the image
        torch.testing.assert_close(second[key], first[key], rtol=1e-5, atol=2e-5)


def test_kept_samples_take_their_rows_of_the_marched_samples(trainer):
    """The gather from marched to kept samples: kept samples of a ray are a prefix of its
    marched ones, and rays behind pruned samples start later in the kept rows."""
    model = RadianceModel(denser_field(trainer.field, 5.0), trainer.grid, trainer.model.march)
    samples = ray_marching(*pixel_rays(*camera(trainer)), model.grid, model.march)
    with torch.no_grad():
        sigma = model.field.density(samples.positions)
    kept = prune_samples(samples, sigma, model.early_stop_eps).samples
    rows = _marched_rows(samples.ray_offsets, kept)
    assert 0 < kept.n_samples < 0.8 * samples.n_samples
    for name in ("ray_indices", "t_starts", "t_ends", "positions", "directions"):
        assert torch.equal(getattr(samples, name)[rows], getattr(kept, name))
    naive = torch.arange(kept.n_samples)  # a wrong gather: the first kept rows, no shift
    assert not torch.equal(samples.t_starts[naive], kept.t_starts)


@pytest.fixture(scope="module")
def coded_model(trainer):
    """A random field with appearance codes (dense enough to see) and a learned environment on
    the trained grid."""
    cfg = FieldConfig(n_levels=8, log2_hashmap_size=14, finest_resolution=128.0, hidden=32, appearance_dim=4,
                      environment=True)
    torch.manual_seed(3)
    field = NGPField(trainer.field.aabb, cfg, n_images=5)
    with torch.no_grad():
        field.environment.weight.normal_(0.0, 1.0)
        field.encoding.params.uniform_(-1.0, 1.0)
        field.appearance.weight.normal_(0.0, 1.0)
        field.density_mlp[-1].weight[0] += 1.0
    return RadianceModel(field, trainer.grid, trainer.model.march)


def test_appearance_codes_colour_the_view(trainer, coded_model):
    c2w, intr = camera(trainer)
    mean = render_view(coded_model, c2w, intr, W, H, background=0.5)
    rays = pixel_rays(c2w, intr)
    assert float(mean["opacity"].max()) > 0.5
    assert_same_image(mean, pruned_render(coded_model, *rays, 0.5))  # None: the mean training code
    explicit = render_view(coded_model, c2w, intr, W, H, background=0.5,
                           appearance_code=coded_model.field.appearance.weight.mean(0))
    torch.testing.assert_close(explicit["rgb"], mean["rgb"], rtol=0, atol=1e-6)
    other = render_view(coded_model, c2w, intr, W, H, background=0.5, appearance_code=torch.tensor([10.0, -10, 5, 0]))
    assert (other["rgb"] - mean["rgb"]).abs().max() > 1e-2
    torch.testing.assert_close(other["opacity"], mean["opacity"])  # the code changes colour only


@pytest.mark.parametrize("supersample, chunk, background", [(1, None, 0.5), (2, None, 0.5), (2, 37, None)])
def test_other_codes_colour_the_same_samples_as_their_own_renders(trainer, coded_model, supersample, chunk,
                                                                  background):
    c2w, intr = camera(trainer)
    model = RadianceModel(denser_field(coded_model.field, -1.0), trainer.grid, trainer.model.march)  # partly clear
    codes = [torch.tensor([10.0, -10, 5, 0]), None, coded_model.field.appearance.weight[3]]
    shared = render_view(model, c2w, intr, W, H, background=background, supersample=supersample, chunk=chunk,
                         appearance_code=codes[0], other_codes=codes[1:])
    assert shared["other_rgb"].shape == (2, H, W, 3)
    assert float(shared["opacity"].min()) < 0.9 < float(shared["opacity"].max())  # the background shows somewhere
    images = [shared["rgb"], *shared["other_rgb"]]
    for code, image in zip(codes, images, strict=True):
        alone = render_view(model, c2w, intr, W, H, background=background, supersample=supersample,
                            chunk=chunk, appearance_code=code)
        assert "other_rgb" not in alone
        torch.testing.assert_close(image, alone["rgb"], rtol=0, atol=1e-6)
        torch.testing.assert_close(shared["opacity"], alone["opacity"], rtol=0, atol=1e-6)
        torch.testing.assert_close(shared["depth"], alone["depth"], rtol=0, atol=1e-6)
    assert min((a - b).abs().max() for a, b in [images[:2], images[1:]]) > 1e-3  # three colourings


def test_appearance_code_mistakes_are_refused(trainer, coded_model):
    c2w, intr = camera(trainer)
    with pytest.raises(ValueError, match=r"\[4\] float"):
        render_view(coded_model, c2w, intr, W, H, appearance_code=torch.zeros(5))
    with pytest.raises(ValueError, match="no appearance codes"):  # through Trainer.render_image
        trainer.render_image(c2w, intr, W, H, appearance_code=torch.zeros(4))
    with pytest.raises(ValueError, match="other_codes given, but this field has no appearance codes"):
        trainer.render_image(c2w, intr, W, H, other_codes=(None,))
    with pytest.raises(ValueError, match=r"\[4\] float"):
        render_view(coded_model, c2w, intr, W, H, other_codes=(torch.zeros(3),))
