import torch

from nerfexp.data.rays import RandomRays, WholeImages
from nerfexp.data.views import Views
from nerfexp.geometry.cameras import look_at
from nerfexp.geometry.lenses import Intrinsics, distort, distortion_vector

# each view its own lens (fx, fy, cx, cy): a centred pinhole, an off-centre one with fx != fy, and one with
# radial distortion, so a ray traced through another view's lens lands off its pixel's centre
LENS_PARAMS = [[6.0, 6.0, 3.5, 2.5], [5.0, 7.0, 3.0, 2.0], [8.0, 6.5, 4.0, 3.0]]
LENS_K1 = [0.0, 0.0, 0.1]


def make_views(n=3, h=5, w=7):
    eyes = torch.tensor([[4.0, 0.0, 1.0], [0.0, -4.0, 2.0], [-3.0, 1.0, 0.5]])[:n]
    c2w = look_at(eyes, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    rgba = torch.rand(n, h, w, 4, generator=torch.Generator().manual_seed(0))
    lenses = Intrinsics(torch.tensor(LENS_PARAMS[:n], dtype=torch.float64),
                        torch.stack([distortion_vector({"k1": k1}) for k1 in LENS_K1[:n]]),
                        torch.zeros(n, dtype=torch.bool))
    return Views(rgba=rgba, c2w=c2w, intrinsics=lenses)


def image_coordinates(views: Views, n: int, direction: torch.Tensor) -> torch.Tensor:
    """(u, v) [..., 2] where world directions [..., 3] of view ``n``'s camera cross its image: the forward
    model (project, distort, scale and shift: ``nerfexp.geometry.lenses``'s docstring), in float64."""
    d_cam = direction.double() @ views.c2w[n, :3, :3].double()  # R^T d: back into the camera frame, down -z
    p = torch.stack([d_cam[..., 0] / -d_cam[..., 2], -d_cam[..., 1] / -d_cam[..., 2]], -1)  # y down
    lens = views.intrinsics[n]
    fx, fy, cx, cy = lens.params.tolist()
    p_d = distort(p, lens.distortion, lens.fisheye)
    return torch.stack([fx * p_d[..., 0] + cx, fy * p_d[..., 1] + cy], -1)


def test_random_rays_carry_the_colour_of_the_pixel_they_pass_through():
    views = make_views()
    background = torch.ones(3)
    batch = next(iter(RandomRays(views, background, batch_rays=64, seed=0)))
    target = views.rgb_on(background)
    for origin, direction, rgb in zip(batch["origins"], batch["directions"], batch["rgb"]):
        n = int(torch.argmin(torch.linalg.vector_norm(views.c2w[:, :3, 3] - origin, dim=-1)))
        assert torch.allclose(views.c2w[n, :3, 3], origin)
        u, v = image_coordinates(views, n, direction).tolist()
        j, i = u - 0.5, v - 0.5  # pixel centres are integers here
        assert abs(j - round(j)) < 1e-4 and abs(i - round(i)) < 1e-4
        torch.testing.assert_close(rgb, target[n, round(i), round(j)])
    assert len(batch["origins"].unique(dim=0)) == 3  # every view, so every lens, was drawn


def test_random_rays_are_repeatable_by_seed():
    views = make_views()
    a = next(iter(RandomRays(views, torch.ones(3), 32, seed=1)))["rgb"]
    b = next(iter(RandomRays(views, torch.ones(3), 32, seed=1)))["rgb"]
    c = next(iter(RandomRays(views, torch.ones(3), 32, seed=2)))["rgb"]
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_whole_images_are_composited_on_the_background():
    views = make_views()
    for n in (1, 2):  # an off-centre lens and a distorted one: each image's rays through its own lens
        item = WholeImages(views, torch.zeros(3))[n]
        assert item["origins"].shape == (5, 7, 3) and item["index"] == n
        torch.testing.assert_close(item["rgb"], views.rgba[n, ..., :3] * views.rgba[n, ..., 3:])
        i, j = torch.meshgrid(torch.arange(5.0), torch.arange(7.0), indexing="ij")
        centres = torch.stack([j + 0.5, i + 0.5], -1).double()
        torch.testing.assert_close(image_coordinates(views, n, item["directions"]), centres, rtol=0, atol=1e-4)


def test_a_ray_stream_started_at_batch_k_continues_the_stream_from_its_start():
    views = Views(rgba=torch.rand(3, 4, 5, 4), c2w=torch.eye(4).expand(3, 4, 4),
                  intrinsics=Intrinsics.pinhole(3.0, 4, 5, (3,)))
    stream = iter(RandomRays(views, torch.ones(3), batch_rays=16, seed=7))
    batches = [next(stream) for _ in range(5)]
    resumed = next(iter(RandomRays(views, torch.ones(3), batch_rays=16, seed=7, start=3)))
    assert resumed.keys() == batches[3].keys() == {"origins", "directions", "rgb", "view", "seed"}
    assert all(torch.equal(resumed[k], batches[3][k]) for k in ("origins", "directions", "rgb", "view"))
    assert resumed["seed"] == batches[3]["seed"]
    # and the stream does not repeat itself: other batches, other seeds
    assert len({b["seed"] for b in batches}) == 5 and not torch.equal(batches[3]["rgb"], batches[4]["rgb"])
    other = next(iter(RandomRays(views, torch.ones(3), batch_rays=16, seed=8, start=3)))
    assert other["seed"] != resumed["seed"] and not torch.equal(other["rgb"], resumed["rgb"])
