"""Pygame picture of the MPA leg of Fig. 2, in the style of Gymnasium's classic-control envs.

The side view shows the ankle pinned on the ground at world (0, 0), the hip on a vertical slider
rail at (0, X) inside a linear bushing block, and the knee in front of the hip-ankle line. The
extensor MPA runs along the front of the femur and pulls a cable wrapped on the knee pulley
(radius r, Eq. 11); the flexor MPA and its wire span the chord l_Mf between the femur point at L1
and the tibia point at L2 from the knee (Eq. 10, 12). Each MPA is shaded from light grey (0 bar)
to red (p_max) and drawn thicker with pressure. The dashed green tick on the rail is the reference
height X̂.

pygame is imported only when a :class:`LegRenderer` is built, so ``import mpa_gym`` never needs it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from gymnasium.error import DependencyNotInstalled

from mpa_gym.model.leg import kinematics
from mpa_gym.model.params import Params, check_range

Color = tuple[int, int, int]
Vec = tuple[float, float]

BACKGROUND: Color = (255, 255, 255)
GROUND: Color = (90, 90, 90)
RAIL: Color = (150, 150, 150)
LINK: Color = (70, 70, 80)
PULLEY: Color = (205, 205, 215)
PIN: Color = (30, 30, 30)
HIP_BLOCK: Color = (60, 110, 170)
REFERENCE: Color = (30, 150, 60)
CABLE: Color = (40, 40, 40)
TEXT: Color = (0, 0, 0)
MPA_EMPTY: Color = (190, 190, 190)  # 0 bar
MPA_FULL: Color = (230, 25, 25)  # p_max

VIEW_HEIGHT_M = 1.0  # [m] world height shown; the ground sits GROUND_MARGIN_M above the bottom
VIEW_WIDTH_M = 0.8  # [m] world width shown
GROUND_MARGIN_M = 0.025  # [m] strip below the ground line (hatching)
HIP_COLUMN = 0.3  # fraction of the width left of the rail

LINK_WIDTH_M = 0.02  # [m] drawn thickness of femur and tibia
HIP_BLOCK_M = (0.09, 0.06)  # [m] width and height of the linear bushing block
MPA_SWELL = 1.0  # an MPA at p_max is drawn (1 + MPA_SWELL) times as thick as at 0 bar


def _lerp(a: Color, b: Color, s: float) -> Color:
    return (round(a[0] + s * (b[0] - a[0])), round(a[1] + s * (b[1] - a[1])),
            round(a[2] + s * (b[2] - a[2])))


def _along(p: Vec, u: Vec, d: float) -> Vec:
    return (p[0] + d * u[0], p[1] + d * u[1])


class LegRenderer:
    """Draws the leg at hip height X; ``rgb_array`` frames headless, ``human`` frames in a window.

    Parameters
    ----------
    params : Params
        Leg geometry (``params.leg``: Lo, Lu, L1, L2, r) and MPA resting length
        (``params.mpa.L0``), Tab. A1/A2.
    p_max_bar : float
        [bar] Pressure drawn as fully red and fully swollen; pressures are clipped to
        [0, p_max_bar].
    human : bool
        Open a window (``pygame.display.set_mode``) and show every frame at ``fps``.
    fps : float
        [1/s] Frame rate of the window in human mode (the envs pass their control rate).
    width, height : int
        [px] Frame size. The scale is fixed, ``min(height / 1.0 m, width / 0.8 m)`` px per m
        (600 px/m for the default 480 x 600), so the picture does not move with X; the frame
        shows heights from −0.025 m to 0.975 m.
    """

    def __init__(self, params: Params, p_max_bar: float, human: bool = False, fps: float = 50.0,
                 width: int = 480, height: int = 600) -> None:
        try:
            import pygame
            from pygame import gfxdraw
        except ImportError as e:
            raise DependencyNotInstalled(
                'pygame is not installed, run `pip install "pygame>=2.5"`'
            ) from e
        self._pg: Any = pygame
        self._gfx: Any = gfxdraw
        self.params = params
        self.p_max_bar = check_range("p_max_bar", p_max_bar, 0.0, low_open=True, unit="bar")
        self.human = bool(human)
        self.fps = float(check_range("fps", fps, 0.0, low_open=True, unit="1/s"))
        self.width = int(check_range("width", width, 64, unit="px"))
        self.height = int(check_range("height", height, 64, unit="px"))
        self.scale = min(self.height / VIEW_HEIGHT_M, self.width / VIEW_WIDTH_M)  # [px/m]
        self._col0 = round(HIP_COLUMN * self.width)  # pixel column of world x = 0
        self._row0 = round(self.height - GROUND_MARGIN_M * self.scale)  # pixel row of y = 0

        self.surf = pygame.Surface((self.width, self.height))
        self.screen: Any = None
        self.clock: Any = None
        if self.human:
            pygame.display.init()
            self.screen = pygame.display.set_mode((self.width, self.height))
            pygame.display.set_caption("MPA leg")
            self.clock = pygame.time.Clock()
        self.font: Any = None
        try:
            pygame.font.init()
            self.font = pygame.font.Font(None, max(12, round(0.03 * self.height)))
        except (pygame.error, ImportError, OSError, AttributeError):
            self.font = None  # pygame built without SDL_ttf: draw no text

    # ------------------------------------------------------------------ coordinates
    def _px(self, p: Vec) -> Vec:
        """World (x, y) [m] -> pixel (column, row) as floats; rows grow downward."""
        return (self._col0 + p[0] * self.scale, self._row0 - p[1] * self.scale)

    def _ipx(self, p: Vec) -> tuple[int, int]:
        c, r = self._px(p)
        return round(c), round(r)

    def hip_pixel(self, x_m: float) -> tuple[int, int]:
        """(column, row) of the hip joint centre in the returned frame for hip height x_m."""
        return self._ipx((0.0, float(x_m)))

    # ------------------------------------------------------------------ primitives
    def _capsule(self, p: Vec, q: Vec, width_px: float, color: Color) -> None:
        """A thick segment with rounded ends from world p to world q, anti-aliased."""
        a, b = self._px(p), self._px(q)
        dx, dy = b[0] - a[0], b[1] - a[1]
        n = math.hypot(dx, dy)
        h = 0.5 * width_px
        if n > 1e-9:
            ox, oy = -dy / n * h, dx / n * h
            poly = [(a[0] + ox, a[1] + oy), (b[0] + ox, b[1] + oy),
                    (b[0] - ox, b[1] - oy), (a[0] - ox, a[1] - oy)]
            self._gfx.aapolygon(self.surf, poly, color)
            self._gfx.filled_polygon(self.surf, poly, color)
        rad = max(1, round(h))
        for c in (a, b):
            self._gfx.aacircle(self.surf, round(c[0]), round(c[1]), rad, color)
            self._gfx.filled_circle(self.surf, round(c[0]), round(c[1]), rad, color)

    def _disc(self, p: Vec, radius_px: float, color: Color, ring: Color | None = None) -> None:
        c, r = self._ipx(p)
        rad = max(1, round(radius_px))
        self._gfx.aacircle(self.surf, c, r, rad, color)
        self._gfx.filled_circle(self.surf, c, r, rad, color)
        if ring is not None:
            self._gfx.aacircle(self.surf, c, r, rad, ring)

    def _line(self, p: Vec, q: Vec, color: Color, width_px: int = 1) -> None:
        self._pg.draw.line(self.surf, color, self._px(p), self._px(q), width_px)

    def _mpa_style(self, pressure_bar: float) -> tuple[Color, float]:
        """Colour and drawn thickness [px] of an MPA at the given pressure."""
        s = float(np.clip(pressure_bar, 0.0, self.p_max_bar)) / self.p_max_bar
        width = max(6.0, self.params.mpa.D0 * self.scale) * (1.0 + MPA_SWELL * s)
        return _lerp(MPA_EMPTY, MPA_FULL, s), width

    # ------------------------------------------------------------------ drawing
    def _scenery(self, x_ref_m: float) -> None:
        pg, surf = self._pg, self.surf
        # ground line with hatching below
        g = self._row0
        pg.draw.line(surf, GROUND, (0, g), (self.width, g), 3)
        step = max(6, round(0.02 * self.scale))
        for c in range(-step, self.width + step, step):
            pg.draw.aaline(surf, GROUND, (c + step, g + 2), (c, g + step + 2))
        # slider rail (x = 0) and its top bracket
        top = self._px((0.0, VIEW_HEIGHT_M))[1]
        half = max(2, round(0.004 * self.scale))
        pg.draw.rect(surf, RAIL, pg.Rect(self._col0 - half, 0, 2 * half + 1,
                                         round(self._px((0.0, 0.05))[1] - top)))
        # reference height X̂: dashed tick across the rail with a marker on the left
        c, r = self._ipx((0.0, x_ref_m))
        reach = round(0.1 * self.scale)
        dash = max(4, round(0.012 * self.scale))
        for c0 in range(c - reach, c + reach, 2 * dash):
            pg.draw.line(surf, REFERENCE, (c0, r), (min(c0 + dash, c + reach), r), 3)
        m = c - reach
        self._gfx.aatrigon(surf, m - 10, r - 6, m - 10, r + 6, m, r, REFERENCE)
        self._gfx.filled_trigon(surf, m - 10, r - 6, m - 10, r + 6, m, r, REFERENCE)

    def _leg(self, x_m: float, pe_bar: float, pf_bar: float) -> None:
        leg, mpa = self.params.leg, self.params.mpa
        Lo, Lu, r = leg.Lo, leg.Lu, leg.r
        X = x_m
        # Knee in front of the hip-ankle line: ankle angle α from the law of cosines.
        cos_a = (Lu * Lu + X * X - Lo * Lo) / (2.0 * Lu * max(X, 1e-9))
        alpha = math.acos(min(1.0, max(-1.0, cos_a)))
        ankle: Vec = (0.0, 0.0)
        hip: Vec = (0.0, X)
        knee: Vec = (Lu * math.sin(alpha), Lu * math.cos(alpha))
        # unit vectors from the knee along the femur (to the hip) and the tibia (to the ankle)
        df = math.hypot(hip[0] - knee[0], hip[1] - knee[1]) or 1.0
        uf: Vec = ((hip[0] - knee[0]) / df, (hip[1] - knee[1]) / df)
        ut: Vec = (-knee[0] / Lu, -knee[1] / Lu)
        # outward (front) normals: perpendicular to each link, away from the other link
        nf: Vec = (uf[1], -uf[0])
        if nf[0] * ut[0] + nf[1] * ut[1] > 0.0:
            nf = (-nf[0], -nf[1])
        nt: Vec = (ut[1], -ut[0])
        if nt[0] * uf[0] + nt[1] * uf[1] > 0.0:
            nt = (-nt[0], -nt[1])
        # actuator lengths L_e, L_f (Eq. 11, 12), evaluated just inside the reachable heights
        lo, hi = leg.x_domain
        kin = kinematics(min(max(X, lo + 1e-6), hi - 1e-6), leg, mpa)
        link_px = LINK_WIDTH_M * self.scale

        # flexor (inside): MPA from the femur point at L1, wire to the tibia point at L2 (Eq. 10);
        # drawn under the links so that its end cap hides behind the femur
        a_f = _along(knee, uf, leg.L1)
        a_t = _along(knee, ut, leg.L2)
        l_mf = math.hypot(a_f[0] - a_t[0], a_f[1] - a_t[1])
        u_ch: Vec = ((a_t[0] - a_f[0]) / l_mf, (a_t[1] - a_f[1]) / l_mf) if l_mf > 0 else ut
        body_f = min(max(float(kin.Lf), 0.02), l_mf)
        self._line(a_f, a_t, CABLE, 2)
        color, w = self._mpa_style(pf_bar)
        self._capsule(a_f, _along(a_f, u_ch, body_f), w, color)

        # knee pulley under the links
        self._disc(knee, r * self.scale, PULLEY, ring=LINK)
        self._capsule(ankle, knee, link_px, LINK)
        self._capsule(knee, hip, link_px, LINK)
        for a in (a_f, a_t):  # flexor attachment pins
            self._disc(a, 3, PULLEY, ring=PIN)

        # extensor (outside): MPA along the front of the femur from Lo/2 above the knee, then a
        # cable tangent to the pulley, wrapped over its front and clamped on the tibia side
        top = _along(_along(knee, uf, 0.5 * Lo), nf, r)
        t_f = (knee[0] + r * nf[0], knee[1] + r * nf[1])
        t_t = (knee[0] + r * nt[0], knee[1] + r * nt[1])
        body_e = min(max(float(kin.Le), 0.02), 0.5 * Lo)
        end_e = _along(top, uf, -body_e)
        th_f, th_t = math.atan2(nf[1], nf[0]), math.atan2(nt[1], nt[0])
        sweep = (th_f - th_t) % (2.0 * math.pi)  # clockwise over the front, π − β
        arc = [self._px((knee[0] + r * math.cos(th_f - sweep * k / 16),
                         knee[1] + r * math.sin(th_f - sweep * k / 16))) for k in range(17)]
        self._line(end_e, t_f, CABLE, 3)
        self._pg.draw.lines(self.surf, CABLE, False, arc, 3)
        self._disc(t_t, 4, CABLE)
        self._capsule(_along(knee, uf, 0.5 * Lo), top, 4, LINK)  # bracket on the femur
        color, w = self._mpa_style(pe_bar)
        self._capsule(top, end_e, w, color)

        # joints
        self._disc(knee, 5, PIN)
        c, g = self._ipx(ankle)
        base = round(0.03 * self.scale)
        self._gfx.filled_trigon(self.surf, c, g, c - base, g, c, g - base // 2, LINK)
        self._gfx.filled_trigon(self.surf, c, g, c + base, g, c, g - base // 2, LINK)
        self._disc(ankle, 6, PIN)
        self._disc(ankle, 3, PULLEY)

        # linear bushing block at the hip; its centre pixel keeps the block colour (ring only)
        bw, bh = HIP_BLOCK_M[0] * self.scale, HIP_BLOCK_M[1] * self.scale
        hc, hr = self.hip_pixel(X)
        block = self._pg.Rect(round(hc - bw / 2), round(hr - bh / 2), round(bw), round(bh))
        self._pg.draw.rect(self.surf, HIP_BLOCK, block, border_radius=4)
        self._pg.draw.rect(self.surf, PIN, block, width=1, border_radius=4)
        self._gfx.aacircle(self.surf, hc, hr, 6, PIN)
        self._gfx.aacircle(self.surf, hc, hr, 5, PIN)

    def _text(self, x_m: float, x_ref_m: float, pe_bar: float, pf_bar: float, t_s: float
              ) -> None:
        if self.font is None:
            return
        lines = [
            (f"t = {t_s:7.3f} s", TEXT),
            (f"X = {1e3 * x_m:6.1f} mm", HIP_BLOCK),
            (f"X = {1e3 * x_ref_m:6.1f} mm", REFERENCE),  # X̂: hat drawn below
            (f"P'e = {pe_bar:5.2f} bar (extensor)", _lerp(TEXT, MPA_FULL, 0.7)),
            (f"P'f = {pf_bar:5.2f} bar (flexor)", _lerp(TEXT, MPA_FULL, 0.7)),
        ]
        row = 6
        for i, (s, color) in enumerate(lines):
            img = self.font.render(s, True, color)
            col = self.width - img.get_width() - 8
            self.surf.blit(img, (col, row))
            if i == 2:  # the font has no combining circumflex: hat the X of X̂ by hand
                w = self.font.size("X")[0]
                hat = [(col + 1, row), (col + w / 2, row - 3), (col + w - 1, row)]
                self._pg.draw.aalines(self.surf, color, False, hat)
            row += img.get_height() + 4

    def draw(self, x_m: float, x_ref_m: float, pressure_bar: np.ndarray, t_s: float
             ) -> np.ndarray:
        """Draw the leg at hip height x_m; return the frame (height, width, 3) uint8. In human mode
        also show it in a window at `fps` (pump events, tick the clock).

        ``pressure_bar`` is (P'_e, P'_f) in bar, extensor first; the picture clips it to
        [0, p_max_bar], the text prints it as given.
        """
        x_m, x_ref_m, t_s = float(x_m), float(x_ref_m), float(t_s)
        for name, v in (("x_m", x_m), ("x_ref_m", x_ref_m), ("t_s", t_s)):
            if not math.isfinite(v):
                raise ValueError(f"{name}={v!r} must be finite")
        p = np.asarray(pressure_bar, dtype=float).reshape(-1)
        if p.shape != (2,) or not np.all(np.isfinite(p)):
            raise ValueError(f"pressure_bar={pressure_bar!r} must be two finite pressures "
                             "(extensor, flexor) in bar")
        pe, pf = float(p[0]), float(p[1])

        self.surf.fill(BACKGROUND)
        self._scenery(x_ref_m)
        self._leg(x_m, pe, pf)
        self._text(x_m, x_ref_m, pe, pf, t_s)

        if self.human and self.screen is not None:
            self.screen.blit(self.surf, (0, 0))
            self._pg.event.pump()
            self.clock.tick(self.fps)
            self._pg.display.flip()
        return np.ascontiguousarray(
            np.transpose(np.array(self._pg.surfarray.pixels3d(self.surf)), axes=(1, 0, 2))
        )

    def close(self) -> None:
        """Close the window (human mode); the renderer draws nothing afterwards."""
        if self.screen is not None:
            self._pg.display.quit()
            self.screen = None
            self.clock = None
        self.human = False
