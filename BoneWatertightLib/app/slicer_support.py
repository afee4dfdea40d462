"""The Slicer panel's and self-tests' decisions, kept apart from Qt so CI can test them.

``BoneWatertight/BoneWatertight.py`` imports Qt and runs only inside 3D Slicer; what it decides
(when Apply may be clicked and what a click does, when the threshold preview shows and hides,
which thresholds Auto may write into the parameter node, whether a self-test installs open3d
or skips) lives here as plain Python, and the widget only wires these objects to its buttons,
timers and cursor. Standard library and the parameter schema only.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Callable, Mapping, Optional

from ..params import SCHEMA

# ----------------------------------------------------------------------------------------
# Apply / Cancel / open3d install


@dataclass(frozen=True)
class ButtonState:
    """What the Apply button shows: its text, whether it is enabled, its tooltip and whether
    the application shows a busy cursor."""

    text: str
    enabled: bool
    tooltip: str
    busyCursor: bool = False


class ApplyGuard:
    """State machine of the Apply button.

    ``idle`` --click--> (install open3d if needed: ``installing`` --> ``idle``) --> ``running``
    --click--> ``cancelling`` --> ``idle``. While open3d installs, pip pumps Qt events for every
    line it prints, so a click queued meanwhile reaches the widget again: :meth:`click` then
    answers ``"ignore"``, and the button is disabled with a busy cursor. A second click while
    cancelling is ignored too. Transitions out of order raise RuntimeError (a bug).
    """

    IDLE, INSTALLING, RUNNING, CANCELLING = "idle", "installing", "running", "cancelling"

    def __init__(self):
        self.state = self.IDLE

    # -- what a click does

    def click(self) -> str:
        """``"start"`` (idle), ``"cancel"`` (running: now cancelling) or ``"ignore"``."""
        if self.state == self.IDLE:
            return "start"
        if self.state == self.RUNNING:
            self.state = self.CANCELLING
            return "cancel"
        return "ignore"

    def requestCancel(self) -> bool:
        """Cancel a running run (e.g. the scene is closing); True if one was running."""
        if self.state == self.RUNNING:
            self.state = self.CANCELLING
            return True
        return self.state == self.CANCELLING

    @property
    def cancelRequested(self) -> bool:
        return self.state == self.CANCELLING

    @property
    def busy(self) -> bool:
        """Installing or running: the inputs and the other buttons must wait."""
        return self.state != self.IDLE

    # -- transitions

    def _move(self, allowed, to):
        if self.state not in allowed:
            raise RuntimeError(f"Apply guard: cannot go from {self.state} to {to}")
        self.state = to

    def beginInstall(self) -> None:
        self._move((self.IDLE,), self.INSTALLING)

    def endInstall(self) -> None:
        self._move((self.INSTALLING,), self.IDLE)

    def beginRun(self) -> None:
        self._move((self.IDLE,), self.RUNNING)

    def endRun(self) -> None:
        self._move((self.RUNNING, self.CANCELLING), self.IDLE)

    @contextlib.contextmanager
    def installing(self):
        self.beginInstall()
        try:
            yield self
        finally:
            self.endInstall()

    @contextlib.contextmanager
    def running(self):
        self.beginRun()
        try:
            yield self
        finally:
            self.endRun()

    # -- what the button shows

    def button(self, inputsReady: bool) -> ButtonState:
        if self.state == self.INSTALLING:
            return ButtonState("Installing open3d...", False,
                               "open3d is being installed; Apply is available when it is done.", True)
        if self.state == self.RUNNING:
            return ButtonState("Cancel", True, "Stop the run; nothing will be changed.")
        if self.state == self.CANCELLING:
            return ButtonState("Cancelling...", False, "The run stops at its next progress step.")
        if inputsReady:
            return ButtonState("Apply", True, "Run the reconstruction.")
        return ButtonState("Apply", False, "Select a CT volume, a segmentation and the bone segment first.")


# ----------------------------------------------------------------------------------------
# threshold preview


class PreviewController:
    """When the live threshold preview shows and when it goes away.

    Every show re-arms the hide timer, whatever asked for it (a slider step, Auto), so no
    path leaves an overlay that never goes; nothing shows while the preview is switched off
    or a run is going. The widget passes ``show``/``hide`` (the MRML preview) and
    ``armHideTimer``/``disarmHideTimer`` (a single-shot QTimer whose timeout calls
    :meth:`hideNow`).
    """

    def __init__(self, show: Callable[[], None], hide: Callable[[], None],
                 armHideTimer: Callable[[], None], disarmHideTimer: Callable[[], None]):
        self._show, self._hide = show, hide
        self._arm, self._disarm = armHideTimer, disarmHideTimer
        self.shown = False

    def thresholdsChanged(self, enabled: bool, running: bool) -> bool:
        """A threshold changed (slider step, typed value, Auto); True if shown."""
        if not enabled or running:
            return False
        self._show()
        self.shown = True
        self._arm()
        return True

    def autoApplied(self, enabled: bool, running: bool) -> bool:
        """Auto wrote its proposal: the same rule as a slider step (values may be unchanged,
        so no valueChanged signal comes)."""
        return self.thresholdsChanged(enabled, running)

    def previewToggled(self, enabled: bool) -> None:
        if not enabled:
            self.hideNow()

    def hideNow(self) -> None:
        self._disarm()
        self._hide()
        self.shown = False


# ----------------------------------------------------------------------------------------
# Auto thresholds


def clamp_threshold_proposal(proposal: Mapping[str, float]) -> tuple:
    """``({"theta_max", "h0", "ht"}, notes)``: Auto's proposal inside the schema's ranges.

    On extended-HU CT with metal the proposed theta_max can exceed the field's maximum (the
    parameter node's WithinRange would raise); each value is clamped to its declared range
    and the order HT < H0 < theta_max is kept one step apart. ``notes`` says what was limited.
    """
    specs = {name: SCHEMA[name] for name in ("theta_max", "h0", "ht")}
    values, notes = {}, []

    def limit(name, value, low, high):
        spec = specs[name]
        clamped = min(max(float(value), low), high)
        if clamped != float(value):
            notes.append(f"{spec.label} {float(value):g} {spec.unit} limited to {clamped:g} {spec.unit}")
        values[name] = clamped

    t, h, g = specs["theta_max"], specs["h0"], specs["ht"]
    limit("theta_max", proposal["theta_max"], t.minimum, t.maximum)
    limit("h0", proposal["h0"], h.minimum, min(h.maximum, values["theta_max"] - (h.step or 1.0)))
    limit("ht", proposal["ht"], g.minimum, min(g.maximum, values["h0"] - (g.step or 1.0)))
    return values, notes


# ----------------------------------------------------------------------------------------
# self-tests that need open3d

TEST_INSTALL_VARIABLE = "BONEWATERTIGHT_TEST_INSTALL"


def dependency_test_plan(importable: bool, environ: Optional[Mapping[str, str]] = None) -> str:
    """``"run"`` (open3d is there), ``"install"`` (try pip once) or ``"skip"`` for a Slicer
    self-test that needs open3d, which no extension build step installs.

    Set BONEWATERTIGHT_TEST_INSTALL=0 on machines that must not download (~400 MB): the test
    then skips at once and says why.
    """
    if importable:
        return "run"
    value = (os.environ if environ is None else environ).get(TEST_INSTALL_VARIABLE, "1")
    return "skip" if value.strip().lower() in ("0", "no", "false", "off") else "install"


def dependency_skip_message(reason: str) -> str:
    return (f"SKIPPED: open3d is not available ({reason}). Install it into Slicer's Python "
            "(pip_install('open3d>=0.18') in the Python console, or Apply in the module "
            f"panel) to run this test; {TEST_INSTALL_VARIABLE}=0 skips without trying.")
