"""The bus budget's arithmetic against the numbers worked out by hand in reference/devices.md and
reference/can.md and issue 31 (a Sync Read of two servos at the XM430's factory baud)."""

from __future__ import annotations

import pytest

from acquisition.devices.bus_budget import (
    SerialLink,
    can_bus_load,
    can_frame_bits,
    servo_ceiling_hz,
    servo_read_s,
    sync_read_bytes,
)


def test_a_sync_read_of_two_servos_is_the_papers_580_bits():
    request, status = sync_read_bytes(2, 10)  # current + velocity + position, addresses 126–135
    assert request + 2 * status == 58  # 16 + 2 × 21 bytes: 580 bits at 8N1
    link = SerialLink(57_600, latency_timer_s=0.0)
    assert servo_read_s(link, 2, 10, return_delay=0) == pytest.approx(580 / 57_600)
    ceiling = servo_ceiling_hz(link, 2, 10, return_delay=250)  # two return delays of 500 µs: ≈ 90 Hz
    assert ceiling == pytest.approx(1 / (580 / 57_600 + 0.001))


def test_the_adapters_latency_timer_caps_a_fast_bus_near_60_hz():
    """What ROBOTIS users report (DynamixelSDK issues 59, 288, 330): 16 ms of latency timer per read."""
    fast = SerialLink(4_000_000)
    assert 55 < servo_ceiling_hz(fast, 2, 16, return_delay=0) < 63
    assert servo_ceiling_hz(SerialLink(4_000_000, 0.001), 2, 16, 0) > 800
    # a reply that ends a USB packet exactly goes at once: no timer to wait for
    assert SerialLink(1_000_000).adapter_wait_s(62) == 0 and SerialLink(1_000_000).adapter_wait_s(63) == 0.016


def test_can_frames_count_their_stuff_bits_and_the_interframe_space():
    assert can_frame_bits(8) == 135  # 111 bits + 24 stuff bits at most (reference/can.md)
    assert can_frame_bits(8, worst_case=False) == 111
    assert can_frame_bits(0) == 47 + 8
    assert can_bus_load({8: 1000}, 1_000_000) == pytest.approx(0.135)
    with pytest.raises(ValueError, match="0 to 8"):
        can_frame_bits(9)
