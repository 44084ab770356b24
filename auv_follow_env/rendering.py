"""pygame drawing for AUVFollowEnv: target, true reference, follower, trails, the fixes the
follower received (v1) and a scale bar.

The frame is ``SIZE`` x ``SIZE`` pixels showing ``SPAN_M`` metres in each direction, centred on
the midpoint of the follower and the true reference, x to the right and y up: a world point
(x, y) is drawn at pixel column ``SIZE / 2 + (x - cx) * SCALE`` and row ``SIZE / 2 - (y - cy) *
SCALE`` (truncated to int; :func:`to_pixel`), ``SCALE = SIZE / SPAN_M`` pixels per metre.

Only pygame's display (``human``) and font modules are initialised, never ``pygame.init()``: that
would also open the audio device (ALSA errors on headless machines), which rendering never needs.
``rgb_array`` initialises no display at all (surfaces and fonts work without one).
"""

from __future__ import annotations

import math
import os

import numpy as np

__all__ = ["SIZE", "SPAN_M", "SCALE", "FIX_COLOUR", "NEWEST_FIX_COLOUR", "NEWEST_FIX_RADIUS", "to_pixel",
           "Renderer"]

SIZE = 600  #: window/frame size [px] (frames are (SIZE, SIZE, 3) uint8)
SPAN_M = 6.0  #: metres across the frame, centred on the follower/reference midpoint
SCALE = SIZE / SPAN_M  #: pixels per metre

_TARGET = (200, 60, 40)
_REF = (40, 140, 60)
_FOLLOWER = (30, 80, 200)
_BG = (235, 244, 250)
#: older received fixes (v1): hollow circles of radius 4 px
FIX_COLOUR = (230, 150, 40)
#: the newest received fix (v1): a filled disc of radius NEWEST_FIX_RADIUS px, black outline, its age as text
NEWEST_FIX_COLOUR = (170, 20, 170)
NEWEST_FIX_RADIUS = 7


def to_pixel(x: float, y: float, cx: float, cy: float) -> tuple[int, int]:
    """(column, row) of the world point (x, y) [m] in a frame centred on (cx, cy) [m] (y up)."""
    return int(SIZE / 2 + (x - cx) * SCALE), int(SIZE / 2 - (y - cy) * SCALE)


class Renderer:
    """Draws frames of one env. ``mode``: "human" (a window, paced at ``fps``) or "rgb_array"."""

    def __init__(self, mode: str, fps: int) -> None:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")  # (the import's banner on stdout)
        try:
            import pygame
        except ImportError as exc:  # pragma: no cover - pygame is a dependency
            raise ImportError("rendering needs pygame: pip install pygame") from exc
        self.pg = pygame
        self.mode = mode
        self.fps = fps
        self.window = None
        self.clock = None
        if mode == "human":
            try:
                pygame.display.init()  # not pygame.init(): that would start the mixer (audio) too
                self.window = pygame.display.set_mode((SIZE, SIZE))
            except pygame.error as exc:
                driver = os.environ.get("SDL_VIDEODRIVER")
                raise RuntimeError(f"render_mode='human' cannot open a window ({exc}; SDL_VIDEODRIVER="
                                   f"{driver!r}): use render_mode='rgb_array' for frames without a display, or "
                                   f"set SDL_VIDEODRIVER=dummy on a machine without one") from exc
            pygame.display.set_caption("AUVFollow")
            self.clock = pygame.time.Clock()
        pygame.font.init()
        self.font = pygame.font.Font(None, 22)

    def draw(self, trails: list[tuple], t: float, err: float, fixes: list[tuple] | None = None):
        """Draw one frame. ``trails``: (x_f, y_f, psi_f, x_t, y_t, psi_t, x_ref, y_ref) per step,
        the last one now; ``fixes`` (v1, else None): (x, y, measured at [s], arrived at [s]) of each
        received fix, oldest first. Returns the frame ((SIZE, SIZE, 3) uint8) in "rgb_array" mode,
        None in "human" mode."""
        pg = self.pg
        surf = pg.Surface((SIZE, SIZE))
        surf.fill(_BG)
        xf, yf, psf, xt, yt, pst, xr, yr = trails[-1]
        cx, cy = 0.5 * (xf + xr), 0.5 * (yf + yr)

        def px(x: float, y: float) -> tuple[int, int]:
            return to_pixel(x, y, cx, cy)

        arr = np.asarray(trails)
        for cols, colour in (((3, 4), _TARGET), ((6, 7), _REF), ((0, 1), _FOLLOWER)):
            pts = [px(a, b) for a, b in arr[:, cols]]
            if len(pts) > 1:
                pg.draw.lines(surf, colour, False, pts, 2)

        def hull(x: float, y: float, psi: float, colour: tuple) -> None:
            c, s = math.cos(psi), math.sin(psi)
            shape = [(0.35, 0.0), (-0.25, 0.15), (-0.25, -0.15)]
            pg.draw.polygon(surf, colour, [px(x + c * a - s * b, y + s * a + c * b) for a, b in shape])

        hull(xt, yt, pst, _TARGET)
        hull(xf, yf, psf, _FOLLOWER)
        pg.draw.circle(surf, _REF, px(xr, yr), 6, 2)
        legend = [("target", _TARGET), ("true reference", _REF), ("follower", _FOLLOWER)]
        lines = [f"t = {t:5.1f} s   error to true reference = {err:.3f} m"]
        if fixes is not None:
            legend += [("received fixes", FIX_COLOUR), ("newest fix (its age)", NEWEST_FIX_COLOUR)]
            for x, y, _, _ in fixes[:-1]:
                pg.draw.circle(surf, FIX_COLOUR, px(x, y), 4, 2)
            if fixes:
                x, y, meas, arrived = fixes[-1]
                at = px(x, y)
                pg.draw.circle(surf, NEWEST_FIX_COLOUR, at, NEWEST_FIX_RADIUS)
                pg.draw.circle(surf, (0, 0, 0), at, NEWEST_FIX_RADIUS, 1)
                surf.blit(self.font.render(f"{t - meas:.1f} s", True, NEWEST_FIX_COLOUR),
                          (at[0] + NEWEST_FIX_RADIUS + 3, at[1] - 8))
                lines.append(f"newest fix: {t - meas:.2f} s old, arrived {t - arrived:.2f} s ago")
            else:
                lines.append("no fix received yet")
        # 1 m scale bar
        pg.draw.line(surf, (0, 0, 0), (20, SIZE - 20), (20 + int(SCALE), SIZE - 20), 3)
        surf.blit(self.font.render("1 m", True, (0, 0, 0)), (20, SIZE - 42))
        for j, txt in enumerate(lines):
            surf.blit(self.font.render(txt, True, (0, 0, 0)), (10, 10 + 18 * j))
        top = 14 + 18 * len(lines)
        for j, (name, colour) in enumerate(legend):
            surf.blit(self.font.render(name, True, colour), (10, top + 18 * j))
        if self.mode == "human":
            self.window.blit(surf, (0, 0))
            pg.event.pump()
            pg.display.flip()
            self.clock.tick(self.fps)
            return None
        return np.ascontiguousarray(np.transpose(pg.surfarray.array3d(surf), (1, 0, 2)))

    def close(self) -> None:
        if self.window is not None:
            self.pg.display.quit()
            self.window = None
