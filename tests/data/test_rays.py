import torch

from nerfexp.data.rays import RandomRays, WholeImages
from nerfexp.data.views import Views
from nerfexp.geometry.cameras import look_at


def make_views(n=3, h=5, w=7, focal=6.0):
    eyes = torch.tensor([[4.0, 0.0, 1.0], [0.0, -4.0, 2.0], [-3.0, 1.0, 0.5]])[:n]
    c2w = look_at(eyes, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    rgba = torch.rand(n, h, w, 4, generator=torch.Generator().manual_seed(0))
    return Views(rgba=rgba, c2w=c2w, focal=focal)


def test_random_rays_carry_the_colour_of_the_pixel_they_pass_through():
    views = make_views()
    background = torch.ones(3)
    batch = next(iter(RandomRays(views, background, batch_rays=64, seed=0)))
    target = views.rgb_on(background)
    for origin, direction, rgb in zip(batch["origins"], batch["directions"], batch["rgb"]):
        n = int(torch.argmin(torch.linalg.vector_norm(views.c2w[:, :3, 3] - origin, dim=-1)))
        assert torch.allclose(views.c2w[n, :3, 3], origin)
        d_cam = views.c2w[n, :3, :3].T @ direction  # back into the camera frame: looks down -z
        x, y = d_cam[0] / -d_cam[2] * views.focal, d_cam[1] / -d_cam[2] * views.focal
        j, i = x + views.width / 2 - 0.5, views.height / 2 - y - 0.5  # pixel centres are integers here
        assert abs(j - round(j.item())) < 1e-4 and abs(i - round(i.item())) < 1e-4
        torch.testing.assert_close(rgb, target[n, round(i.item()), round(j.item())])


def test_random_rays_are_repeatable_by_seed():
    views = make_views()
    a = next(iter(RandomRays(views, torch.ones(3), 32, seed=1)))["rgb"]
    b = next(iter(RandomRays(views, torch.ones(3), 32, seed=1)))["rgb"]
    c = next(iter(RandomRays(views, torch.ones(3), 32, seed=2)))["rgb"]
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_whole_images_are_composited_on_the_background():
    views = make_views()
    item = WholeImages(views, torch.zeros(3))[1]
    assert item["origins"].shape == (5, 7, 3) and item["index"] == 1
    torch.testing.assert_close(item["rgb"], views.rgba[1, ..., :3] * views.rgba[1, ..., 3:])


def test_a_ray_stream_started_at_batch_k_continues_the_stream_from_its_start():
    views = Views(rgba=torch.rand(3, 4, 5, 4), c2w=torch.eye(4).expand(3, 4, 4), focal=3.0)
    stream = iter(RandomRays(views, torch.ones(3), batch_rays=16, seed=7))
    batches = [next(stream) for _ in range(5)]
    resumed = next(iter(RandomRays(views, torch.ones(3), batch_rays=16, seed=7, start=3)))
    assert resumed.keys() == batches[3].keys() == {"origins", "directions", "rgb", "seed"}
    assert all(torch.equal(resumed[k], batches[3][k]) for k in ("origins", "directions", "rgb"))
    assert resumed["seed"] == batches[3]["seed"]
    # and the stream does not repeat itself: other batches, other seeds
    assert len({b["seed"] for b in batches}) == 5 and not torch.equal(batches[3]["rgb"], batches[4]["rgb"])
    other = next(iter(RandomRays(views, torch.ones(3), batch_rays=16, seed=8, start=3)))
    assert other["seed"] != resumed["seed"] and not torch.equal(other["rgb"], resumed["rgb"])
