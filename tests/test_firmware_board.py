"""The Black Pill (STM32F411CE) board target builds with Debian's arm-none-eabi-gcc and fits the chip.

Skips with the reason when the cross toolchain is missing (`.ci/run` installs gcc-arm-none-eabi).
Nothing here runs on hardware: it checks the image a flasher would write.
"""

from __future__ import annotations

import shutil
import struct
import subprocess
from pathlib import Path

import pytest

BOARD = Path(__file__).resolve().parents[1] / "firmware" / "boards" / "blackpill-f411"
FLASH_BYTES, RAM_BYTES, STACK_BYTES = 512 * 1024, 128 * 1024, 4 * 1024
RAM_TOP = 0x2000_0000 + RAM_BYTES
IRQ_TIM2, IRQ_USART1 = 28, 37


@pytest.fixture(scope="module")
def toolchain() -> None:
    missing = [t for t in ("make", "arm-none-eabi-gcc", "arm-none-eabi-size", "arm-none-eabi-nm") if shutil.which(t) is None]
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed: apt-get install gcc-arm-none-eabi make (the board target is not built)")


def build(tmp_path: Path, taxels: int) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path / f"taxels-{taxels}"
    proc = subprocess.run(["make", "-C", str(BOARD), f"BUILD={out}", f"TAXELS={taxels}"], capture_output=True, text=True)
    return out / "touchreal-f411.elf", proc


@pytest.mark.parametrize("taxels", [1, 8])
def test_board_image_builds_and_fits_the_stm32f411ce(toolchain, tmp_path, taxels):
    elf, proc = build(tmp_path, taxels)
    assert proc.returncode == 0, proc.stderr
    size = subprocess.run(["arm-none-eabi-size", str(elf)], check=True, capture_output=True, text=True).stdout
    text, data, bss = (int(v) for v in size.splitlines()[1].split()[:3])
    assert 0 < text + data <= FLASH_BYTES
    assert data + bss + STACK_BYTES <= RAM_BYTES
    symbols = {}
    for line in subprocess.run(["arm-none-eabi-nm", str(elf)], check=True, capture_output=True, text=True).stdout.splitlines():
        addr, _, name = line.split(maxsplit=2)
        symbols[name] = int(addr, 16)
    image = elf.with_suffix(".bin").read_bytes()
    assert len(image) == text + data
    vectors = struct.unpack_from("<54I", image)
    assert vectors[0] == RAM_TOP  # initial stack pointer
    assert vectors[1] == symbols["Reset_Handler"] | 1  # Thumb entry points
    assert vectors[16 + IRQ_TIM2] == symbols["TIM2_IRQHandler"] | 1
    assert vectors[16 + IRQ_USART1] == symbols["USART1_IRQHandler"] | 1


def test_board_refuses_more_taxels_than_its_pvdf_inputs(toolchain, tmp_path):
    _, proc = build(tmp_path, 9)
    assert proc.returncode != 0 and "8 PVDF inputs" in proc.stderr
