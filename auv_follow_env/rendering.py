"""pygame drawing for AUVFollowEnv: target, true reference, follower, trails and a scale bar."""

from __future__ import annotations

import math
import os

import numpy as np

SIZE = 600  # window/frame size [px]
SPAN_M = 6.0  # metres across the frame, centred on the follower/reference midpoint

_TARGET = (200, 60, 40)
_REF = (40, 140, 60)
_FOLLOWER = (30, 80, 200)
_BG = (235, 244, 250)


class Renderer:
    def __init__(self, mode: str, fps: int) -> None:
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
            pygame.init()
            pygame.display.init()
            self.window = pygame.display.set_mode((SIZE, SIZE))
            pygame.display.set_caption("AUVFollow")
            self.clock = pygame.time.Clock()
        else:
            os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
            pygame.font.init()
        self.font = pygame.font.Font(None, 22)

    def draw(self, trails: list[tuple], t: float, err: float):
        pg = self.pg
        surf = pg.Surface((SIZE, SIZE))
        surf.fill(_BG)
        xf, yf, psf, xt, yt, pst, xr, yr = trails[-1]
        cx, cy = 0.5 * (xf + xr), 0.5 * (yf + yr)
        scale = SIZE / SPAN_M

        def px(x: float, y: float) -> tuple[int, int]:  # y up on screen
            return int(SIZE / 2 + (x - cx) * scale), int(SIZE / 2 - (y - cy) * scale)

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
        # 1 m scale bar
        pg.draw.line(surf, (0, 0, 0), (20, SIZE - 20), (20 + int(scale), SIZE - 20), 3)
        surf.blit(self.font.render("1 m", True, (0, 0, 0)), (20, SIZE - 42))
        txt = f"t = {t:5.1f} s   error to true reference = {err:.3f} m"
        surf.blit(self.font.render(txt, True, (0, 0, 0)), (10, 10))
        legend = (("target", _TARGET), ("true reference", _REF), ("follower", _FOLLOWER))
        for j, (name, colour) in enumerate(legend):
            surf.blit(self.font.render(name, True, colour), (10, 32 + 18 * j))
        if self.mode == "human":
            self.window.blit(surf, (0, 0))
            pg.event.pump()
            pg.display.flip()
            self.clock.tick(self.fps)
            return None
        return np.transpose(np.array(pg.surfarray.pixels3d(surf)), (1, 0, 2)).copy()

    def close(self) -> None:
        if self.window is not None:
            self.pg.display.quit()
            self.window = None
