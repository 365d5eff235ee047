"""Frozen-camera check: N consecutive bit-identical images = frozen; any change resets."""
import numpy as np
import pytest

from ibvs_perception.core.freeze import FrozenImageCheck, SAMPLE_STRIDE

SHAPE = (480, 752)


def frame(seed=0, shape=SHAPE):
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


@pytest.mark.parametrize('n', [1, 2, 3, 7])
def test_identical_frames_are_frozen_after_exactly_n_repeats(n):
    check = FrozenImageCheck(n)
    img = frame()
    # the first image and its first n - 1 repeats pass, the n-th repeat is frozen
    results = [check.check(img.copy()) for _ in range(n + 3)]
    assert results == [False] * n + [True] * 3
    assert check.frozen and check.identical_frames == n + 2


def test_a_one_pixel_change_resets_anywhere_in_the_image():
    check = FrozenImageCheck(3)
    img = frame()
    for _ in range(4):
        check.check(img.copy())
    assert check.frozen
    # a pixel off the sparse sample (index 1) and one on it (index 0): both reset
    for index in (1, 0, SAMPLE_STRIDE, img.size - 1):
        changed = img.copy()
        changed.flat[index] ^= 1
        assert check.check(changed) is False and check.identical_frames == 0
        img = changed
    assert [check.check(img.copy()) for _ in range(3)] == [False, False, True]


def test_live_noisy_frames_of_a_still_scene_never_freeze():
    check = FrozenImageCheck(1)
    scene = np.full(SHAPE, 120, np.int16)
    rng = np.random.default_rng(4)
    for _ in range(50):
        noisy = np.clip(scene + np.rint(rng.normal(0, 1.5, SHAPE)), 0, 255).astype(np.uint8)
        assert check.check(noisy) is False


def test_shape_and_type_changes_are_not_repeats():
    check = FrozenImageCheck(1)
    img = frame(shape=(4, 6))
    assert check.check(img) is False
    assert check.check(img.reshape(6, 4).copy()) is False      # same bytes, other shape
    assert check.check(img.reshape(6, 4).copy()) is True
    assert check.check(img.reshape(6, 4).astype(np.int16)) is False   # other type
    assert check.check(np.zeros((0, 0), np.uint8)) is False
    assert check.check(np.zeros((0, 0), np.uint8)) is True


def test_the_same_array_object_again_counts_as_a_repeat_and_reset_forgets():
    check = FrozenImageCheck(2)
    img = frame()
    assert [check.check(img) for _ in range(3)] == [False, False, True]
    check.reset()
    assert not check.frozen and check.check(img) is False


@pytest.mark.parametrize('bad', [0, -1, 1.5, 3.0, True, '3', None])
def test_n_is_validated(bad):
    with pytest.raises(ValueError, match='frozen_after_frames'):
        FrozenImageCheck(bad)


def test_numpy_integer_is_accepted():
    assert FrozenImageCheck(np.int64(2)).frozen_after_frames == 2
