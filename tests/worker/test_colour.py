import numpy as np

from worker.colour import linear_to_srgb, linear_to_srgb8, srgb_to_linear


def test_known_values_of_the_piecewise_curve():
    # sRGB 0.5 is 0.21404 linear; below the knee the curve is linear with slope 1/12.92.
    assert np.isclose(srgb_to_linear(np.float32(0.5)), 0.2140411, atol=1e-6)
    assert np.isclose(srgb_to_linear(np.float32(0.04)), 0.04 / 12.92, atol=1e-8)
    assert np.isclose(linear_to_srgb(np.float32(0.001)), 0.01292, atol=1e-7)
    assert linear_to_srgb(np.float32(1.0)) == np.float32(1.0)


def test_round_trip_and_monotonic():
    x = np.linspace(0, 1, 4097, dtype=np.float32)
    assert np.abs(linear_to_srgb(srgb_to_linear(x)) - x).max() < 2e-6
    assert (np.diff(srgb_to_linear(x)) >= 0).all()
    assert srgb_to_linear(x).dtype == np.float32


def test_out_of_range_is_clipped_and_8bit_codes_are_exact():
    assert srgb_to_linear(np.array([-0.5, 2.0])).tolist() == [0.0, 1.0]
    codes = np.arange(256) / 255.0
    assert (linear_to_srgb8(srgb_to_linear(codes)) == np.arange(256)).all()
