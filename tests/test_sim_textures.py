"""Procedural textures: seeded, with the contrast their kind promises, and mip levels that average."""
import numpy as np
import pytest

from common.sim.textures import KINDS, TextureAtlas, TextureError, TextureSpec, build_texture, mip_pyramid


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_builds_deterministically_in_range(kind):
    a = build_texture(TextureSpec(kind, seed=3, resolution=64))
    b = build_texture(TextureSpec(kind, seed=3, resolution=64))
    assert a.dtype == np.float32 and a.ndim == 3 and a.shape[2] == 3
    assert np.array_equal(a, b)
    assert a.min() >= 0 and a.max() <= 1


def test_seeds_change_random_kinds():
    for kind in ("brick", "noise", "poster", "paint"):
        assert not np.array_equal(build_texture(TextureSpec(kind, seed=1, resolution=64)),
                                  build_texture(TextureSpec(kind, seed=2, resolution=64)))


def test_paint_is_texture_poor_and_brick_is_not():
    grey = lambda k: build_texture(TextureSpec(k, seed=0)).mean(axis=2) * 255
    assert grey("paint").std() < 2.0          # about one grey level of mottling
    assert grey("brick").std() > 15.0
    assert grey("poster").std() > 15.0


def test_mip_levels_halve_and_preserve_the_mean():
    img = build_texture(TextureSpec("brick", seed=0, resolution=128))
    levels = mip_pyramid(img)
    assert [l.shape[:2] for l in levels][-1] == (1, 2)
    for a, b in zip(levels[:-1], levels[1:]):
        assert b.shape[0] == a.shape[0] // 2 and b.shape[1] == a.shape[1] // 2
        np.testing.assert_allclose(b.mean(axis=(0, 1)), a.mean(axis=(0, 1)), atol=1e-5)


def test_atlas_indexes_every_level():
    specs = [TextureSpec("checker", resolution=32), TextureSpec("poster", seed=4, resolution=64)]
    atlas = TextureAtlas.build(specs)
    for i, s in enumerate(specs):
        lvl0 = build_texture(s)
        w, h, off = atlas.width[i, 0], atlas.height[i, 0], atlas.offset[i, 0]
        np.testing.assert_array_equal(atlas.texels[off:off + w * h].reshape(h, w, 3), lvl0)
    assert atlas.period_m[0, 0] > 0 and atlas.period_m[1, 0] < 0  # checker tiles, poster is stretched


@pytest.mark.parametrize("kwargs, match", [
    (dict(kind="marble"), "unknown texture kind"),
    (dict(kind="brick", resolution=100), "power of two"),
    (dict(kind="brick", color=(300, 0, 0)), "colour"),
    (dict(kind="brick", size_m=(1.0, 0.0)), "size_m"),
])
def test_bad_specs(kwargs, match):
    with pytest.raises(TextureError, match=match):
        TextureSpec(**kwargs)
