"""What the viewer shows, as one value: :class:`ViewerState` (data, frame, selection,
layer toggles, camera, playback). The app and every panel read and change it; it holds
no GUI handle and no server, so it can be built and checked without a browser.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from mvviz.scene.geometry import (
    ALL_FRUSTA_MAX_CAMERAS,
    MANY_CAMERAS_FRUSTUM_WIDTH,
    LayerToggles,
    Selection,
    ViewerData,
    prepare,
)
from pipeline.data.scene import Scene
from pipeline.results.store import PipelineResults

if TYPE_CHECKING:
    from pipeline.body.arrays import BodyModelData
    from pipeline.body.model import BodyModel

# The camera panel's image: as wide as the panel (400 px) by default, so a frame change
# sends ~12 kB for it; 640 px (the stored frames' width) for a sharper look.
PANEL_WIDTHS = (400, 640)


@dataclass
class ViewerState:
    """What the viewer shows: data, frame, selection, layer toggles, playback."""

    data: ViewerData
    frame: int = 0
    selection: Selection = field(default_factory=Selection)
    layers: LayerToggles = field(default_factory=LayerToggles)
    camera: int = 0  # view shown in the image panel
    panel_image_width: int = PANEL_WIDTHS[0]  # px of the image panel's picture
    playing: bool = False
    speed: float = 1.0
    loop: bool = True

    @property
    def scene(self) -> Scene:
        return self.data.scene

    @property
    def results(self) -> PipelineResults:
        return self.data.results

    @classmethod
    def create(
        cls, scene: Scene, results: PipelineResults, model: BodyModel | BodyModelData | None = None
    ) -> ViewerState:
        data = prepare(scene, results, model)
        names = data.joint_set.names
        joint = next((names.index(n) for n in ("right_wrist", "left_wrist") if n in names), 0)
        track = 0 if data.num_tracks else None
        many = len(scene.rig) > ALL_FRUSTA_MAX_CAMERAS  # what a frame change sends
        layers = LayerToggles(detections2d_panel_camera_only=many)
        if many:
            layers.frustum_image_width = MANY_CAMERAS_FRUSTUM_WIDTH
        return cls(data=data, selection=Selection(track=track, joint=joint), layers=layers)

    def snapshot(self) -> ViewerState:
        """A copy safe to read while GUI callbacks keep mutating this one."""
        return dataclasses.replace(self, layers=dataclasses.replace(self.layers))
