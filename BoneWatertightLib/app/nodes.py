"""The run service on MRML nodes: what the Slicer logic and panel call.

One run on nodes is: check the request without touching a voxel (:func:`_plan_many`), guard
the scene (:class:`RunGuard`: closing it, or removing an input or output node, cancels the
run), export the CT and the segments through the MRML adapter (:mod:`..mrml`), reconstruct,
and only then store the surfaces (models, report attributes, optionally segments written
back and intermediate-result nodes), undoing what was written should storing fail half-way
(:class:`_SceneChanges`). The reconstruction goes through the run service either way:

- in this process (:func:`run_many_on_nodes`, :func:`run_on_nodes`: the logic's ``process``
  and ``processMany``): :func:`.run.reconstruct_joint`, after :func:`.run.load_pipeline` has
  imported open3d in a helper thread while the progress keeps coming;
- in a child process, for a panel whose GUI thread must stay free (issue 13):
  :func:`start_many_on_nodes` exports on the caller's thread and starts
  :class:`.child.ChildRun` (the project's command line, whose :func:`.run.run_joint` calls
  :func:`.run.reconstruct_joint`); the returned :class:`ChildNodesRun` is polled from a timer
  (never blocks) and cancelled within a second; :func:`finish_many_on_nodes` stores its result
  with the same code as the in-process run.

Progress is one [0, 1] scale from the first moment: the export, the import, then the
pipeline's own [0, 1] mapped onto [PIPELINE_START, 1]. MRML is touched on the caller's thread
only. This module never imports ``slicer``: the adapter does the node work.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import SimpleITK as sitk
import vtk

from .. import mrml
from ..errors import CancelledError, InputError
from ..mesh.surface import Surface
from ..params import Parameters
from ..report import to_json
from . import run
from .summaries import summarize_joint

# Overall progress fraction where each step of the run's own first phase starts; the
# pipeline's [0, 1] is mapped onto [PIPELINE_START, 1].
EXPORT_VOLUME_START = 0.0
EXPORT_SEGMENT_START = 0.01
IMPORT_START = 0.02
PIPELINE_START = 0.04
# Neighbours farther than margin + segment_dilation + this from the bones to reconstruct are
# left out: the pipeline crops to the targets + margin + band, and the band is at most
# segment_dilation + 3 mm (segments beyond the crop cannot compete, and cannot block a run by
# overlapping each other far away).
NEIGHBOUR_REACH_SLACK_MM = 10.0
CHILD_STARTING_MESSAGE = "Starting the reconstruction process"


# ---------------------------------------------------------------------------------------
# scene guard and progress
# ---------------------------------------------------------------------------------------

class RunGuard:
    """Cancels a run whose scene closes or whose nodes leave the scene (SPEC 5: never write
    into a closed scene or a removed node).

    Observes the scene's StartCloseEvent and NodeRemovedEvent while the run lasts; the run's
    progress calls :meth:`check`, and the run checks once more before it touches the scene.
    Use as a context manager (observers are removed on exit).
    """

    def __init__(self, scene, nodes=(), onCancel=None):
        self.scene = scene
        self.nodes = [n for n in nodes if n is not None]
        self.reason: Optional[str] = None
        # called once when the run is to be cancelled (a child process is stopped at once)
        self.onCancel = onCancel
        self._tags = []
        if scene is not None:
            self._tags = [scene.AddObserver(scene.StartCloseEvent, self._onClose),
                          scene.AddObserver(scene.NodeRemovedEvent, self._onNodeRemoved)]

    def _onClose(self, caller=None, event=None):
        if self.reason is None:
            self.reason = "The scene was closed during the run"
            self._notify()

    def _onNodeRemoved(self, caller=None, event=None):
        if self.reason is not None:
            return
        for node in self.nodes:
            if not self.scene.IsNodePresent(node):
                self.reason = f"'{node.GetName()}' was removed from the scene during the run"
                self._notify()
                return

    def _notify(self):
        if self.onCancel is not None:
            self.onCancel()

    def check(self) -> None:
        """CancelledError if the scene closed or a node of the run was removed."""
        if self.reason is not None:
            raise CancelledError(f"{self.reason}; nothing was written.")

    def close(self) -> None:
        for tag in self._tags:
            self.scene.RemoveObserver(tag)
        self._tags = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class RunProgress:
    """The progress callback of one run on nodes: its first phase (export, imports), then
    the pipeline's, on one [0, 1] scale; checks the :class:`RunGuard` at every call.

    ``callback(fraction, message)`` returning False cancels (CancelledError), as in the library.
    """

    def __init__(self, callback=None, guard: Optional[RunGuard] = None,
                 pipeline_start: float = PIPELINE_START):
        self.callback = callback
        self.guard = guard
        self.pipeline_start = pipeline_start

    def __call__(self, fraction: float, message: str = "") -> None:
        if self.guard is not None:
            self.guard.check()
        if self.callback is not None and self.callback(fraction, message) is False:
            raise CancelledError("Cancelled by the user; nothing was changed.")

    def pipeline(self):
        """The callback to hand to the pipeline (its [0, 1] mapped onto ours)."""
        start = self.pipeline_start

        def report(fraction, message=""):
            if self.guard is not None:
                self.guard.check()
            if self.callback is None:
                return True
            return self.callback(start + (1.0 - start) * fraction, message)
        return report


def export_joint_inputs(volumeNode, segmentationNode, segmentIds, neighbourIds, params: Parameters,
                        progress: Optional[RunProgress] = None):
    """(CT, :class:`~BoneWatertightLib.mrml.SegmentLabels`) for a joint run: the bones and
    their neighbours as one label image on the CT grid (neighbours out of the pipeline's reach
    are left out), reporting progress per step."""
    if progress is not None:
        progress(EXPORT_VOLUME_START, "Reading the CT volume")
    ct = mrml.volume_to_sitk(volumeNode)
    message = "Reading the segment" if len(segmentIds) + len(neighbourIds) == 1 else "Reading the segments"
    if progress is not None:
        progress(EXPORT_SEGMENT_START, message)

    def layer(fraction, text):
        if progress is not None and fraction > 0:
            progress(EXPORT_SEGMENT_START + (IMPORT_START - EXPORT_SEGMENT_START) * fraction, text)

    labels = mrml.segments_to_sitk_labels(
        segmentationNode, list(segmentIds) + list(neighbourIds), volumeNode, required=segmentIds,
        reach_mm=params.margin + params.segment_dilation + NEIGHBOUR_REACH_SLACK_MM, progress=layer)
    return ct, labels


# ---------------------------------------------------------------------------------------
# what a run is asked for
# ---------------------------------------------------------------------------------------

def _as_parameters(params) -> Parameters:
    if params is None:
        return Parameters()
    if isinstance(params, Parameters):
        return params
    if isinstance(params, dict):
        return Parameters().replace(**params)
    raise InputError(f"params must be a Parameters object or a dict, got {type(params).__name__}.")


def _per_segment(value, segmentIds, what: str) -> list:
    """A list aligned with ``segmentIds`` from None, a sequence of that length or a dict."""
    if value is None:
        return [None] * len(segmentIds)
    if isinstance(value, dict):
        unknown = set(value) - set(segmentIds)
        if unknown:
            raise InputError(f"{what} given for segment(s) not reconstructed: {', '.join(sorted(unknown))}.")
        return [value.get(s) for s in segmentIds]
    value = list(value)
    if len(value) != len(segmentIds):
        raise InputError(f"{len(value)} {what} for {len(segmentIds)} segments: give one per segment "
                         "(None: a new one).")
    return value


def _neighbour_ids(segmentationNode, segmentIds, neighbours) -> list:
    segmentation = segmentationNode.GetSegmentation()
    every = [segmentation.GetNthSegmentID(i) for i in range(segmentation.GetNumberOfSegments())]
    if neighbours in (None, "auto", True):
        # written back by an earlier run: a copy of its source segment, not another bone
        return [s for s in every if s not in segmentIds
                and not segmentation.GetSegment(s).HasTag(mrml.SOURCE_SEGMENT_TAG)]
    if neighbours in ("none", False):
        return []
    if isinstance(neighbours, str):
        raise InputError(f"neighbours must be 'auto', 'none' or a list of segment IDs, got '{neighbours}'.")
    chosen = list(neighbours)
    for segmentId in chosen:
        mrml.check_segment(segmentationNode, segmentId)
    both = [s for s in chosen if s in segmentIds]
    if both:
        raise InputError(f"Segment(s) {', '.join(both)} are both reconstructed and neighbours: give "
                         "each segment one role.")
    return list(dict.fromkeys(chosen))


@dataclass
class _ManyRun:
    """What a joint run on nodes was asked for, checked before any work (shared by the
    in-process and the child-process run)."""

    scene: object
    volumeNode: object
    segmentationNode: object
    segmentIds: list
    parameters: Parameters
    outputs: list
    names: list
    neighbourIds: list
    addAsSegments: bool
    showIntermediates: bool
    colorByDistance: bool

    @property
    def guardedNodes(self) -> tuple:
        """The nodes whose removal cancels the run: the inputs and the given output models."""
        return (self.volumeNode, self.segmentationNode, *[n for n in self.outputs if n is not None])

    def pipelineTargets(self, labels) -> tuple:
        """(target label values, neighbours argument, competing segment IDs) of the
        reconstruction for the exported ``labels`` (neighbours that are empty, outside the CT
        or out of reach are not in it)."""
        competing = [s for s in self.neighbourIds if s in labels.values]
        return ([labels.values[s] for s in self.segmentIds], "auto" if competing else "none",
                competing)


def _plan_many(volumeNode, segmentationNode, segmentIds, outputModelNodes, params, scene,
               neighbours, addAsSegments, showIntermediates, colorByDistance, modelNames) -> _ManyRun:
    """Every check of a joint run on nodes that needs no voxel (InputError before any work)."""
    parameters = _as_parameters(params)
    if showIntermediates and not parameters.keep_intermediates:
        parameters = parameters.replace(keep_intermediates=True)
    parameters.validate()
    if isinstance(segmentIds, str):
        segmentIds = [segmentIds]
    segmentIds = list(segmentIds or [])
    if scene is None:
        scene = (volumeNode.GetScene() if volumeNode is not None else None) or (
            segmentationNode.GetScene() if segmentationNode is not None else None)
    if scene is None:
        raise InputError("The input nodes are not in a scene.")
    if not segmentIds:
        mrml.check_segment(segmentationNode, "")
    for segmentId in segmentIds:
        mrml.check_segment(segmentationNode, segmentId)
    if len(set(segmentIds)) != len(segmentIds):
        raise InputError("The same segment is asked for twice; give each segment once.")
    outputs = _per_segment(outputModelNodes, segmentIds, "output models")
    for node in outputs:
        if node is not None and not node.IsA("vtkMRMLModelNode"):
            raise InputError("The output node must be a model node.")
    given = [n for n in outputs if n is not None]
    if len({n.GetID() or id(n) for n in given}) != len(given):
        raise InputError("The same output model is given for two segments; give each bone its own.")
    names = _per_segment(modelNames, segmentIds, "model names")
    neighbourIds = _neighbour_ids(segmentationNode, segmentIds, neighbours)
    if addAsSegments:
        mrml.check_write_back(segmentationNode)
    return _ManyRun(scene=scene, volumeNode=volumeNode, segmentationNode=segmentationNode,
                    segmentIds=segmentIds, parameters=parameters, outputs=outputs, names=names,
                    neighbourIds=neighbourIds, addAsSegments=bool(addAsSegments),
                    showIntermediates=bool(showIntermediates), colorByDistance=bool(colorByDistance))


# ---------------------------------------------------------------------------------------
# storing a result (only after it succeeded)
# ---------------------------------------------------------------------------------------

@dataclass
class JointNodesResult:
    """What a joint run on nodes made: one model node per bone (``modelNodes[i]`` for
    ``segmentIds[i]``), the segments written back (``addedSegmentIds``, same order, empty unless
    asked for), the other segments handed to the pipeline as neighbours
    (``neighbourSegmentIds``; ``skippedSegments``: segment ID -> why one was not: empty, outside
    the CT, out of reach), the intermediate-result nodes, and the pipeline's JointResult (or a
    child run's :class:`.child.ChildJoint`, with the same attributes)."""

    modelNodes: list
    segmentIds: list
    result: object
    addedSegmentIds: list = field(default_factory=list)
    neighbourSegmentIds: list = field(default_factory=list)
    skippedSegments: dict = field(default_factory=dict)
    intermediateNodes: list = field(default_factory=list)

    @property
    def warnings(self) -> list:
        return [w for b in self.result.bones for w in b.report.warnings]

    def summaryLines(self) -> list:
        return summarize_joint(self.result)


def _with_distances(bone) -> Surface:
    surface = bone.surface
    if mrml.DISTANCE_ARRAY not in surface.point_data and bone.distance_to_constraints is not None:
        d = np.asarray(bone.distance_to_constraints, dtype=np.float64)
        if d.shape == (surface.n_vertices,):
            surface = surface.copy()
            surface.point_data[mrml.DISTANCE_ARRAY] = d
    return surface


class _SceneChanges:
    """What a successful run writes, undone if writing fails half-way: nodes it added, models
    it replaced (their mesh, report attributes and display settings), segments it added."""

    _DISPLAY = ("ScalarVisibility", "ActiveScalarName", "ColorNodeID", "ScalarRangeFlag", "ScalarRange")
    _ATTRIBUTES = (mrml.REPORT_ATTRIBUTE, mrml.JOINT_REPORT_ATTRIBUTE, mrml.SOURCE_SEGMENT_ATTRIBUTE)

    def __init__(self, scene, segmentationNode):
        self.scene = scene
        self.segmentationNode = segmentationNode
        self.added = []
        self.models = []
        self.segments = []

    def addNode(self, node):
        self.added.append(node)
        return node

    def replacingModel(self, node):
        display = node.GetDisplayNode()
        state = None if display is None else {k: getattr(display, "Get" + k)() for k in self._DISPLAY}
        attributes = {k: node.GetAttribute(k) for k in self._ATTRIBUTES}
        self.models.append((node, node.GetPolyData(), display, state, attributes))

    def undo(self):
        segmentation = self.segmentationNode.GetSegmentation()
        for segmentId in self.segments:
            segmentation.RemoveSegment(segmentId)
        for node in reversed(self.added):
            mrml.remove_node(node)
        for node, poly, display, state, attributes in self.models:
            node.SetAndObservePolyData(poly)
            for key, value in attributes.items():
                if value is None:
                    node.RemoveAttribute(key)
                else:
                    node.SetAttribute(key, value)
            created = node.GetDisplayNode()
            if created is not display:
                # the failed run made a display node: the model gets its own back (or none)
                node.SetAndObserveDisplayNodeID(display.GetID() if display is not None else None)
                if created is not None and created.GetScene() is not None:
                    created.GetScene().RemoveNode(created)
            if display is not None:
                display.SetActiveScalar(state["ActiveScalarName"], vtk.vtkAssignAttribute.POINT_DATA)
                if display.GetColorNodeID() != state["ColorNodeID"]:  # "" stands for none
                    display.SetAndObserveColorNodeID(state["ColorNodeID"] or "")
                display.SetScalarRangeFlag(state["ScalarRangeFlag"])
                display.SetScalarRange(*state["ScalarRange"])
                display.SetScalarVisibility(state["ScalarVisibility"])


def _source_key(segmentationNode, segmentId) -> str:
    return f"{segmentationNode.GetID()}/{segmentId}"


def _store_many(plan: _ManyRun, guard: RunGuard, joint, labels) -> JointNodesResult:
    """The success half of a joint run on nodes: ``joint`` (the pipeline's JointResult, or a
    child run's ChildJoint with the same attributes) into models, report attributes and, on
    request, segments and intermediate-result nodes. Should any of it fail, what was written
    is undone and the error propagates."""
    guard.check()  # the scene may have closed after the last progress report
    scene, segmentationNode = plan.scene, plan.segmentationNode
    segmentation = segmentationNode.GetSegmentation()
    segNames = [segmentation.GetSegment(s).GetName() or s for s in plan.segmentIds]
    surfaces = [_with_distances(b) for b in joint.bones]
    prepared = None
    if plan.addAsSegments:
        prepared = mrml.prepare_segments_without_overlap(
            segmentationNode, plan.volumeNode, [(f"{n} watertight", s) for n, s in zip(segNames, surfaces)])
        guard.check()
    out = JointNodesResult(modelNodes=[], segmentIds=list(plan.segmentIds), result=joint,
                           neighbourSegmentIds=plan.pipelineTargets(labels)[2],
                           skippedSegments=dict(labels.skipped))
    changes = _SceneChanges(scene, segmentationNode)
    jointJson = to_json(joint.report) if len(joint.bones) > 1 else None
    try:
        for segmentId, bone, surface, node, name, segName in zip(out.segmentIds, joint.bones, surfaces,
                                                                 plan.outputs, plan.names, segNames):
            if node is None:
                node = changes.addNode(scene.AddNewNodeByClass(
                    "vtkMRMLModelNode", name or scene.GenerateUniqueName(f"{segName} watertight")))
                node.CreateDefaultDisplayNodes()
                if node.GetDisplayNode() is not None:
                    node.GetDisplayNode().SetColor(*segmentation.GetSegment(segmentId).GetColor())
            else:
                changes.replacingModel(node)
            mrml.update_model_node(node, surface, colorByDistance=plan.colorByDistance)
            node.SetAttribute(mrml.REPORT_ATTRIBUTE, to_json(bone.report))
            node.SetAttribute(mrml.SOURCE_SEGMENT_ATTRIBUTE, _source_key(segmentationNode, segmentId))
            if jointJson is not None:
                node.SetAttribute(mrml.JOINT_REPORT_ATTRIBUTE, jointJson)
            else:
                node.RemoveAttribute(mrml.JOINT_REPORT_ATTRIBUTE)
            out.modelNodes.append(node)
        if prepared is not None:
            colors = [segmentation.GetSegment(s).GetColor() for s in out.segmentIds]
            changes.segments = mrml.add_prepared_segments(segmentationNode, prepared, colors, out.segmentIds)
            out.addedSegmentIds = list(changes.segments)
        if plan.showIntermediates:
            for bone, segName in zip(joint.bones, segNames):
                if getattr(bone, "intermediates", None):
                    nodes = mrml.add_intermediate_nodes(scene, bone.intermediates,
                                                        prefix=f"BoneWatertight {segName}")
                    for node in nodes:
                        changes.addNode(node)
                    out.intermediateNodes += nodes
    except BaseException:
        changes.undo()
        out.modelNodes, out.addedSegmentIds, out.intermediateNodes = [], [], []
        raise
    return out


def previous_output_models(scene, segmentationNode, segmentIds) -> dict:
    """{segment ID: model node} of the models an earlier run made from these segments (their
    SOURCE_SEGMENT_ATTRIBUTE), for a panel that replaces its previous results on a new run."""
    wanted = {_source_key(segmentationNode, s): s for s in segmentIds}
    found = {}
    for n in range(scene.GetNumberOfNodesByClass("vtkMRMLModelNode")):
        node = scene.GetNthNodeByClass(n, "vtkMRMLModelNode")
        segmentId = wanted.get(node.GetAttribute(mrml.SOURCE_SEGMENT_ATTRIBUTE) or "")
        if segmentId is not None and segmentId not in found:
            found[segmentId] = node
    return found


# ---------------------------------------------------------------------------------------
# the runs
# ---------------------------------------------------------------------------------------

def _begin(plan: _ManyRun, guard: RunGuard, progress):
    """The part both runs share after the checks: (RunProgress, CT, SegmentLabels)."""
    report = RunProgress(progress, guard)
    ct, labels = export_joint_inputs(plan.volumeNode, plan.segmentationNode, plan.segmentIds,
                                     plan.neighbourIds, plan.parameters, report)
    return report, ct, labels


def run_many_on_nodes(volumeNode, segmentationNode, segmentIds, outputModelNodes=None, params=None,
                      progress=None, scene=None, *, neighbours="auto", addAsSegments: bool = False,
                      showIntermediates: bool = False, colorByDistance: bool = False,
                      modelNames=None) -> JointNodesResult:
    """Reconstruct several bones of one segmentation together from MRML nodes (SPEC §5b).

    :param segmentIds: the segments to reconstruct (one model each, in this order).
    :param outputModelNodes: models to replace on success: None (new ones named
        "<segment> watertight"), a list aligned with ``segmentIds`` (None entries: new), or a
        dict segment ID -> model node.
    :param neighbours: "auto" (default: every other segment of the segmentation competes for
        the joints, and no surface enters it; segments written back by an earlier run are
        copies of their sources and left out), "none", or a list of segment IDs.
    :param addAsSegments: also write the surfaces into the segmentation as new segments
        "<segment> watertight", sharing one label map layer (no voxel in two of them).
    :param showIntermediates, colorByDistance: as :func:`run_on_nodes`.
    :param modelNames: names of new models (list aligned with segmentIds or dict).
    :return: :class:`JointNodesResult`.
    :raises InputError: bad inputs, overlapping segments (named). ReconstructionError and its
        subclasses (PlausibilityError, SurfaceCheckError) when a bone fails; CancelledError.

    The scene is only modified after every bone succeeded; a failed or cancelled run leaves it
    as it was (also should writing the results fail half-way: what was written is undone).
    Progress, Cancel and the scene-close guard as in :func:`run_on_nodes`. The same run in a
    child process (the GUI thread stays free): :func:`start_many_on_nodes` /
    :func:`finish_many_on_nodes`.
    """
    plan = _plan_many(volumeNode, segmentationNode, segmentIds, outputModelNodes, params, scene,
                      neighbours, addAsSegments, showIntermediates, colorByDistance, modelNames)
    with RunGuard(plan.scene, plan.guardedNodes) as guard:
        report, ct, labels = _begin(plan, guard, progress)
        run.load_pipeline(report, IMPORT_START, PIPELINE_START)
        targets, competing, _ = plan.pipelineTargets(labels)
        joint = run.reconstruct_joint(ct, labels.image, targets, plan.parameters, report.pipeline(),
                                      names=labels.names, neighbours=competing)
        return _store_many(plan, guard, joint, labels)


def run_on_nodes(volumeNode, segmentationNode, segmentId, outputModelNode=None, params=None,
                 progress=None, scene=None, *, addAsSegment: bool = False,
                 showIntermediates: bool = False, colorByDistance: bool = False,
                 modelName: Optional[str] = None, neighbours="auto"):
    """Reconstruct the watertight surface of one bone from MRML nodes.

    Returns ``(modelNode, result)`` (a ReconstructionResult). Every other segment of the
    segmentation is a neighbour by default (``neighbours="auto"``: they compete for the joint
    and the surface never enters them); ``neighbours="none"`` reconstructs the segment alone,
    a list of segment IDs uses those. The scene is only modified after the pipeline succeeded;
    any error (bad input, reconstruction failure, cancel) propagates with the scene unchanged.
    ``progress(fraction, message)`` is called from the first moment (CT and segment export,
    the open3d import) and throughout the pipeline; returning False cancels. Closing the
    scene, or removing an input or the output node, during the run cancels it
    (CancelledError) and nothing is written (:class:`RunGuard`).
    """
    mrml.check_segment(segmentationNode, segmentId)
    out = run_many_on_nodes(volumeNode, segmentationNode, [segmentId], [outputModelNode], params,
                            progress, scene, neighbours=neighbours, addAsSegments=addAsSegment,
                            showIntermediates=showIntermediates, colorByDistance=colorByDistance,
                            modelNames=[modelName])
    return out.modelNodes[0], out.result.bones[0]


class ChildNodesRun:
    """A joint run on nodes whose reconstruction goes on in a child process
    (:class:`.child.ChildRun`), made by :func:`start_many_on_nodes`.

    :meth:`poll` (from a GUI timer) never blocks: it returns ``(fraction, message, finished)``
    on the run's one [0, 1] scale (export, then the child's progress from PIPELINE_START on).
    :meth:`cancel` stops the child within a second. The scene guard (:class:`RunGuard`) stays
    on while the child runs: closing the scene, or removing an input or a given output model,
    cancels the child at once, and :func:`finish_many_on_nodes` then raises CancelledError.
    ``childRun`` is the ChildRun (its ``progress_log``, ``output``, ``command``).
    """

    def __init__(self, plan: _ManyRun, guard: RunGuard, labels, childRun):
        self.plan = plan
        self.guard = guard
        self.labels = labels
        self.childRun = childRun
        self.closed = False
        guard.onCancel = self.cancel

    def poll(self):
        from .child import PollResult

        if self.guard.reason is not None and not self.childRun.cancelled:
            self.childRun.cancel()
        state = self.childRun.poll()
        if self.childRun.proc is None or not self.childRun.progress_log:
            fraction = IMPORT_START
            message = state.message or CHILD_STARTING_MESSAGE
        else:
            fraction = PIPELINE_START + (1.0 - PIPELINE_START) * state.fraction
            message = state.message
        return PollResult(fraction, message, state.finished)

    @property
    def finished(self) -> bool:
        return self.childRun.finished

    def cancel(self) -> None:
        """Stop the child (returns within about a second); the run then ends cancelled."""
        self.childRun.cancel()

    def close(self) -> None:
        """Stop the child if it still runs, remove its files, stop observing the scene."""
        if not self.closed:
            self.closed = True
            try:
                self.childRun.close()
            finally:
                self.guard.onCancel = None
                self.guard.close()


def start_many_on_nodes(volumeNode, segmentationNode, segmentIds, outputModelNodes=None, params=None,
                        progress=None, scene=None, *, neighbours="auto", addAsSegments: bool = False,
                        showIntermediates: bool = False, colorByDistance: bool = False,
                        modelNames=None, python: Optional[str] = None, env: Optional[dict] = None,
                        tempRoot: Optional[str] = None) -> ChildNodesRun:
    """First half of :func:`run_many_on_nodes` with the reconstruction in a child process.

    Checks the inputs, exports the CT and the segments (on this thread: MRML is read here
    only; ``progress`` is called as in run_many_on_nodes during the export), starts the
    child (``python``: the interpreter, default :func:`.child.find_python_slicer`; ``env``: its
    environment; ``tempRoot``: where its private folder goes) and returns at once with a
    :class:`ChildNodesRun`. Poll it from a timer; then :func:`finish_many_on_nodes`. The
    arguments and errors before the run are those of run_many_on_nodes; the scene is not
    touched.
    """
    from .child import ChildRun

    plan = _plan_many(volumeNode, segmentationNode, segmentIds, outputModelNodes, params, scene,
                      neighbours, addAsSegments, showIntermediates, colorByDistance, modelNames)
    guard = RunGuard(plan.scene, plan.guardedNodes)
    try:
        report, ct, labels = _begin(plan, guard, progress)
        report(IMPORT_START, CHILD_STARTING_MESSAGE)
        targets, competing, _ = plan.pipelineTargets(labels)
        # the export made sure every target and neighbour in the label image has voxels
        child = ChildRun(ct, labels.image, targets, labels.names, plan.parameters, neighbours=competing,
                         python=python, env=env, temp_root=tempRoot, check_labels=False)
        child.start()
    except BaseException:
        guard.close()
        raise
    return ChildNodesRun(plan, guard, labels, child)


def finish_many_on_nodes(run: ChildNodesRun, timeout: Optional[float] = None) -> JointNodesResult:
    """Second half: wait for the child (at once when :meth:`ChildNodesRun.poll` said finished;
    ``timeout`` in s, else ChildRunError), then write the surfaces into the model nodes (and
    segments, intermediate nodes) exactly as :func:`run_many_on_nodes` does, and return its
    :class:`JointNodesResult` (``result`` is the child's ChildJoint: ``bones[i].report``,
    ``pairs``, ``report``, typed). The child's error is raised as the library's typed error
    (InputError, ReconstructionError, ...), CancelledError after a cancel, a closed scene or a
    removed node; the scene is then unchanged. The child's files and the scene observers are
    gone afterwards in every case."""
    try:
        run.guard.check()
        joint = run.childRun.result(timeout)
        return _store_many(run.plan, run.guard, joint, run.labels)
    except BaseException:
        if run.guard.reason is not None:
            run.childRun.cancel()
            run.guard.check()  # CancelledError naming why (the scene closed, a node was removed)
        raise
    finally:
        run.close()


# ---------------------------------------------------------------------------------------
# what the panel asks for besides a run
# ---------------------------------------------------------------------------------------

def segment_selection(segmentationNode, segmentIds=(), segmentId: str = "",
                      pickFirst: bool = False) -> list:
    """The segments a panel shows as chosen in ``segmentationNode``: the stored ``segmentIds``
    that exist in it (in their order), else the one ``segmentId`` of an older parameter node,
    else, when ``pickFirst`` (the segmentation was just chosen), its first segment, as the
    single-segment selector does; [] without a segmentation."""
    if segmentationNode is None:
        return []
    segmentation = segmentationNode.GetSegmentation()
    chosen = [s for s in dict.fromkeys(mrml.segment_id_list(segmentIds)) if segmentation.GetSegment(s)]
    if chosen:
        return chosen
    if segmentId and segmentation.GetSegment(segmentId) is not None:
        return [segmentId]
    if pickFirst and segmentation.GetNumberOfSegments():
        return [segmentation.GetNthSegmentID(0)]
    return []


def propose_thresholds(volumeNode, segmentationNode, segmentIds, theta_max: float = 2500.0) -> dict:
    """H0/HT proposal (the panel's Auto) from the HU histogram in and around the segment, or
    the union of several segments (a list of IDs); the pipeline's own estimate, see
    :func:`BoneWatertightLib.stages.autothreshold.propose_thresholds`."""
    from ..stages.autothreshold import propose_thresholds as _propose

    labels = mrml.segments_to_sitk_labels(segmentationNode, mrml.segment_id_list(segmentIds), volumeNode)
    mask = sitk.Cast(sitk.NotEqual(labels.image, 0), sitk.sitkUInt8)
    return _propose(mrml.volume_to_sitk(volumeNode), mask, theta_max=theta_max)
