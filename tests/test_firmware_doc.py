"""docs/firmware.md cannot drift from the code: every row of its reference table is read back
from the constant or default it names, its example frames are what the protocol encodes, its
fault bits are the protocol's, and every number with a unit in its rules is one of the table's."""

from __future__ import annotations

import importlib
import inspect
import math
import re
from pathlib import Path

import pytest

from mpa_gym.hardware import protocol as proto

ROOT = Path(__file__).resolve().parents[1]
DOC = (ROOT / "docs" / "firmware.md").read_text()
# a value's unit → its factor to the unit the code's name carries (``_s``, ``_bar``, Hz, B, ...)
UNITS = {"ms": 1e-3, "s": 1.0, "Hz": 1.0, "bar": 1.0, "B": 1.0, "baud": 1.0, "m": 1.0,
         "m/s": 1.0, "": 1.0}
NUMBER = r"(0x[0-9A-Fa-f]+|\d+(?:\.\d+)?)"


def section(title: str) -> str:
    """The text of ``## title`` up to the next ``## `` heading."""
    return DOC.split(f"## {title}\n")[1].split("\n## ")[0]


def reference_rows() -> list[tuple[str, str, str]]:
    rows = [[c.strip() for c in ln.strip().strip("|").split("|")]
            for ln in section("Reference numbers").splitlines() if ln.startswith("| ")]
    return [(q, v, src.strip("`")) for q, v, src in rows[1:]]  # the header left out


def resolve(source: str):
    """``pkg.module.NAME``, ``pkg.module.NAME[i]``, ``pkg.module.Class.attr`` or
    ``pkg.module.callable(argument)`` (that argument's default) → its value."""
    m = re.fullmatch(r"([\w.]+?)(?:\((\w+)\)|\[(\d+)\])?", source)
    assert m, source
    path, argument, index = m.groups()
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):  # the longest importable module, then attributes
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        break
    if argument is not None:
        return inspect.signature(obj).parameters[argument].default
    return obj if index is None else obj[int(index)]


def numbers(value: str) -> list[float]:
    """``40 ms`` → [0.04]; ``0.6 m, 0.87 m`` → [0.6, 0.87]; ``0xA55A`` → [42330]."""
    out = []
    for num, unit in re.findall(NUMBER + r"\s*(ms|s|Hz|bar|B|baud|m/s|m)?\b", value.strip("`")):
        out.append(int(num, 16) if num.startswith("0x") else float(num) * UNITS[unit or ""])
    return out


@pytest.mark.parametrize(("quantity", "value", "source"), reference_rows())
def test_each_reference_number_is_the_codes(quantity, value, source):
    code = resolve(source)
    if isinstance(code, bytes):  # the sync word, as the bytes are sent
        code = int.from_bytes(code, "big")
    want = list(code) if isinstance(code, tuple) else [code]
    got = numbers(value)
    assert len(got) == len(want), (quantity, value, code)
    for g, w in zip(got, want, strict=True):
        assert math.isclose(g, float(w), rel_tol=1e-12), (quantity, value, source, code)


def test_the_example_frames_are_what_the_protocol_encodes():
    frames = {
        "Command": proto.Command(1, 1000, 1.5e5, 0.5e5),
        "Vent": proto.Vent(2, 2000),
        "Telemetry": proto.Telemetry(7, 12345, 0.8, 0.0, 1.5e5, 0.5e5, 0, 1),
    }
    text = section("Frames").split("### Example frames")[1]
    shown = re.findall(r"^- (\w+),.*?`([0-9a-f ]+)`", text, flags=re.M | re.S)
    assert [name for name, _ in shown] == list(frames)
    for name, hex_bytes in shown:
        assert bytes.fromhex(hex_bytes) == proto.encode(frames[name]), name
        assert proto.decode_frame(bytes.fromhex(hex_bytes)) == frames[name]
    # the stated check value, by the device's table walk
    assert "`0x29B1`" in DOC and proto.crc16_table_walk(b"123456789") == 0x29B1


def test_the_fault_bits_are_the_protocols():
    rows = [[c.strip() for c in ln.strip("|").split("|")]
            for ln in section("Frames").split("### Fault bits")[1].split("###")[0].splitlines()
            if re.match(r"\| \d", ln)]
    assert {int(v): name.strip("`") for v, name, _ in rows} == {
        bit: proto.fault_names(bit)[0] for bit in (proto.FAULT_WATCHDOG_VENT,
                                                   proto.FAULT_OVERPRESSURE, proto.FAULT_SENSOR,
                                                   proto.FAULT_VENTED)}


def test_every_number_in_the_rules_is_a_reference_number():
    """The link, timing and testing sections state limits in prose: each number with a unit
    there is one of the table's values (an example command line's own values, such as
    ``--episode-s 10``, carry no unit and are not limits)."""
    table = {round(x, 12) for _, v, _ in reference_rows() for x in numbers(v)}
    for title in ("What the device does", "The link", "Timing rules the device must keep",
                  "Testing a device"):
        text = re.sub(r"`[^`]*`", "", section(title))  # code spans: flags, file names
        for num, unit in re.findall(NUMBER + r"\s*(ms|Hz|bar|baud|m/s|s|m)\b", text):
            x = round(float(num) * UNITS[unit], 12)
            assert x in table, (title, f"{num} {unit}")


def test_the_emulators_watchdog_flag_defaults_to_its_constant():
    from mpa_gym.agents.cli import build_parser
    from mpa_gym.hardware.emulator import WATCHDOG_S

    assert build_parser().parse_args(["emulate", "--udp"]).watchdog == WATCHDOG_S


def test_readme_and_design_link_the_guide():
    assert "docs/firmware.md" in (ROOT / "README.md").read_text()
    assert "firmware.md" in (ROOT / "docs" / "design.md").read_text()


def test_the_guides_c_crc_is_the_protocols(tmp_path):
    """The C function a device author copies, compiled and run (where a C compiler is): the
    check value, and the CRC of a frame's body as the protocol computes it."""
    import shutil
    import subprocess

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    code = re.search(r"```c\n(.*?)```", DOC, flags=re.S).group(1)
    frame = proto.encode(proto.Command(1, 1000, 1.5e5, 0.5e5))
    body = frame[len(proto.SYNC):-proto.CRC_SIZE]
    src = tmp_path / "crc.c"
    src.write_text("#include <stdint.h>\n#include <stddef.h>\n#include <stdio.h>\n" + code
                   + "int main(void) { static const uint8_t body[] = {"
                   + ", ".join(str(b) for b in body) + "};\n"
                   + '  printf("%04X %04X\\n", crc16_ccitt_false((const uint8_t *)"123456789", 9),'
                   + f" crc16_ccitt_false(body, {len(body)}));\n  return 0;\n}}\n")
    subprocess.run([cc, "-std=c99", "-o", str(tmp_path / "crc"), str(src)], check=True)
    out = subprocess.run([str(tmp_path / "crc")], capture_output=True, text=True, check=True)
    check, of_body = (int(v, 16) for v in out.stdout.split())
    assert check == 0x29B1
    assert of_body == int.from_bytes(frame[-proto.CRC_SIZE:], "little")
