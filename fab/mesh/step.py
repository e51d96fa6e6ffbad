"""STEP (B-rep) model of a relief tile and of the tiled aperture, via build123d / OCCT.

The tile becomes ONE closed solid whose planar faces are exactly the polygons of
``fab.mesh.relief.relief_surface`` (pixel tops, walls, chamfers, back face). Their
edges are made once and shared by both adjacent faces, so the shell is closed by construction:
no sewing, no boolean fusion (one box per pixel fused would take hours). The
aperture is an assembly of located instances of that one solid.

Units are millimetres; the STEP header carries a fixed timestamp so a rerun
writes identical bytes. build123d (and OCP) are imported inside the functions.
"""

import io
import re

import numpy as np

from fab.mesh.chamfer import pinch_depths
from fab.mesh.relief import relief_surface, surface_points_mm

STEP_TIMESTAMP = "2000-01-01T00:00:00"
# A random 8-level tile of N = 175 gives ~80k faces, which builds and writes in about a
# minute on two cores; beyond this count the B-rep route is refused (use the meshes).
MAX_STEP_FACES = 250_000


def step_face_count(levels):
    """Return the number of planar faces the STEP solid of ``levels`` will have.

    Pixel tops, walls, outer walls, the back, and two per chamfered corner (the
    chamfer face and its triangle at z_lo, ``fab.mesh.chamfer``).
    """
    lev = np.asarray(levels, np.int64)
    walls = int((np.diff(lev, axis=1) != 0).sum() + (np.diff(lev, axis=0) != 0).sum())
    chamfers = 2 * len(pinch_depths(lev))
    return lev.size + walls + 2 * (lev.shape[0] + lev.shape[1]) + 1 + chamfers


def tile_solid(relief, surface=None):
    """Build the relief tile as one closed build123d ``Solid`` in millimetres.

    ``surface`` may pass ``relief_surface(relief.levels)`` when already built.
    """
    from build123d import Solid
    from OCP.BRep import BRep_Builder
    from OCP.BRepBuilderAPI import (
        BRepBuilderAPI_MakeEdge,
        BRepBuilderAPI_MakeFace,
        BRepBuilderAPI_MakeVertex,
        BRepBuilderAPI_MakeWire,
    )
    from OCP.gp import gp_Dir, gp_Pln, gp_Pnt
    from OCP.TopoDS import TopoDS_Shell, TopoDS_Solid

    if surface is None:
        surface = relief_surface(relief.levels)
    pts = surface_points_mm(surface, relief).tolist()
    vertices = [BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex() for p in pts]
    edges = {}
    builder = BRep_Builder()
    shell = TopoDS_Shell()
    builder.MakeShell(shell)
    from tqdm import tqdm

    loops = zip(surface.loops, surface.loop_normals.tolist(), strict=True)
    bar = tqdm(loops, total=len(surface.loops), desc="STEP faces", leave=False, disable=None)
    for loop, normal in bar:
        ids = loop.tolist()
        wire = BRepBuilderAPI_MakeWire()
        for a, b in zip(ids, ids[1:] + ids[:1], strict=True):
            key = (a, b) if a < b else (b, a)
            edge = edges.get(key)
            if edge is None:
                edge = BRepBuilderAPI_MakeEdge(vertices[a], vertices[b]).Edge()
                edges[key] = edge
            wire.Add(edge)
        plane = gp_Pln(gp_Pnt(*pts[ids[0]]), gp_Dir(*map(float, normal)))
        builder.Add(shell, BRepBuilderAPI_MakeFace(plane, wire.Wire(), True).Face())
    shell.Closed(True)
    solid = TopoDS_Solid()
    builder.MakeSolid(solid)
    builder.Add(solid, shell)
    return Solid(solid)


def step_bytes(solid, offsets_mm=None, name="tile"):
    """Return a STEP (AP214, mm) file of ``solid``, alone or as an assembly of instances.

    Parameters
    ----------
    solid : build123d.Solid
        The tile, in mm.
    offsets_mm : array_like, shape (M, 3), optional
        With offsets, the file holds the solid once and an assembly ``aperture``
        of M located instances (translation only); without, the bare solid.
        OCCT's writer spends time per instance proportional to the solid's size
        (minutes for 256 dense tiles), so large assemblies go through
        :func:`assembly_step_bytes` on the bare solid's file instead.
    name : str
        Product name of the tile.
    """
    if offsets_mm is None:
        doc, tool = _new_document()
        _add_solid(tool, solid, name)
        return _write_document(doc, name)
    return scene_step_bytes([(name, solid, offsets_mm)], "aperture")


def scene_step_bytes(parts, name):
    """Return a STEP (AP214, mm) assembly ``name`` of several solids, each stored once.

    ``parts``: [(part name, build123d.Solid in mm, offsets (M, 3) mm)]; each offset
    places one located instance of its part (translation only). For small solids (the
    clipped edge tiles): OCCT's writer time grows with instances x solid size.
    """
    from OCP.gp import gp_Trsf, gp_Vec
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDataStd import TDataStd_Name
    from OCP.TopLoc import TopLoc_Location

    doc, tool = _new_document()
    labels = [_add_solid(tool, solid, part) for part, solid, _ in parts]
    assembly = tool.NewShape()
    TDataStd_Name.Set_s(assembly, TCollection_ExtendedString(name))
    for label, (part, _, offsets) in zip(labels, parts, strict=True):
        for n, (x, y, z) in enumerate(np.asarray(offsets, np.float64).tolist()):
            trsf = gp_Trsf()
            trsf.SetTranslation(gp_Vec(x, y, z))
            comp = tool.AddComponent(assembly, label, TopLoc_Location(trsf))
            TDataStd_Name.Set_s(comp, TCollection_ExtendedString(f"{part}_{n}"))
    tool.UpdateAssemblies()
    return _numbered_occurrences(_write_document(doc, name))


_OCCURRENCE_ID = re.compile(rb"NEXT_ASSEMBLY_USAGE_OCCURRENCE\('\d+'")


def _numbered_occurrences(step):
    """Number the assembly occurrences 1, 2, ... in file order.

    OCCT takes their ids from a counter that lives as long as the process, so a
    second scene written by the same process would otherwise differ in these ids.
    """
    count = iter(range(1, 1 << 62))
    return _OCCURRENCE_ID.sub(lambda m: b"NEXT_ASSEMBLY_USAGE_OCCURRENCE('%d'" % next(count), step)


def _new_document():
    """Return (an XCAF document in mm, its shape tool)."""
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDocStd import TDocStd_Document
    from OCP.XCAFApp import XCAFApp_Application
    from OCP.XCAFDoc import XCAFDoc_DocumentTool

    doc = TDocStd_Document(TCollection_ExtendedString("XmlOcaf"))
    app = XCAFApp_Application.GetApplication_s()
    app.NewDocument(TCollection_ExtendedString("MDTV-XCAF"), doc)
    app.InitDocument(doc)
    XCAFDoc_DocumentTool.SetLengthUnit_s(doc, 1e-3)  # document unit: mm
    tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    tool.SetAutoNaming_s(False)
    return doc, tool


def _add_solid(tool, solid, name):
    """Add ``solid`` to the document as a named shape; return its label."""
    from OCP.TCollection import TCollection_ExtendedString
    from OCP.TDataStd import TDataStd_Name

    label = tool.AddShape(solid.wrapped, False)
    TDataStd_Name.Set_s(label, TCollection_ExtendedString(name))
    return label


def _write_document(doc, name):
    """Return the STEP bytes of an XCAF document (header ``name``, pinned timestamp)."""
    from OCP.APIHeaderSection import APIHeaderSection_MakeHeader
    from OCP.IFSelect import IFSelect_ReturnStatus
    from OCP.Interface import Interface_Static
    from OCP.Message import Message, Message_Gravity
    from OCP.STEPCAFControl import STEPCAFControl_Controller, STEPCAFControl_Writer
    from OCP.STEPControl import STEPControl_Controller, STEPControl_StepModelType
    from OCP.TCollection import TCollection_HAsciiString
    from OCP.XSControl import XSControl_WorkSession

    for printer in Message.DefaultMessenger_s().Printers():
        printer.SetTraceLevel(Message_Gravity.Message_Fail)
    STEPCAFControl_Controller.Init_s()
    STEPControl_Controller.Init_s()
    writer = STEPCAFControl_Writer(XSControl_WorkSession(), False)
    writer.SetNameMode(True)
    # colours, layers, properties etc. walk every sub-shape of every instance: off
    for mode in (
        "SetColorMode",
        "SetLayerMode",
        "SetPropsMode",
        "SetSHUOMode",
        "SetDimTolMode",
        "SetMaterialMode",
        "SetVisualMaterialMode",
    ):
        if hasattr(writer, mode):
            getattr(writer, mode)(False)
    header = APIHeaderSection_MakeHeader(writer.Writer().Model())
    if not header.IsDone():
        header = APIHeaderSection_MakeHeader(0)
        header.Apply(writer.Writer().Model())
    header.SetName(TCollection_HAsciiString(name))
    header.SetTimeStamp(TCollection_HAsciiString(STEP_TIMESTAMP))
    header.SetOriginatingSystem(TCollection_HAsciiString("doefab (build123d/OCCT)"))
    Interface_Static.SetIVal_s("write.surfacecurve.mode", 0)  # no pcurves: planar faces only
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    writer.Transfer(doc, STEPControl_StepModelType.STEPControl_AsIs)
    buf = io.BytesIO()
    if writer.WriteStream(buf) != IFSelect_ReturnStatus.IFSelect_RetDone:
        raise RuntimeError("OCCT failed to write the STEP file")
    return buf.getvalue()


_ENTITY = re.compile(rb"^#(\d+) = ", re.M)


def assembly_step_bytes(tile_step, offsets_mm, name="aperture"):
    """Return a STEP assembly of M translated instances of the solid in ``tile_step``.

    Appends to the tile's file the entities OCCT itself writes for an assembly
    (product ``name``, a shape representation with one placement per instance,
    and per instance a NEXT_ASSEMBLY_USAGE_OCCURRENCE with its
    ITEM_DEFINED_TRANSFORMATION), so the tile's geometry is written once and
    placing 256 instances costs milliseconds instead of OCCT's minutes.

    Parameters
    ----------
    tile_step : bytes
        A file from ``step_bytes(solid)`` (one product, one B-rep representation).
    offsets_mm : array_like, shape (M, 3)
        Translation of each instance (mm).
    """
    text = tile_step
    # OCCT writes the product and representation entities first and numbers entities in
    # order, so the head and the tail suffice (a full regex scan of 100 MB takes seconds)
    head, tail = text[: 1 << 20], text[-(1 << 16) :]
    ids = [int(m) for m in _ENTITY.findall(tail)] or [int(m) for m in _ENTITY.findall(text)]
    pd = _find_all(rb"^#(\d+) = PRODUCT_DEFINITION\('design'", head, text)
    rep = _find_all(
        rb"^#(\d+) = ADVANCED_BREP_SHAPE_REPRESENTATION\('[^']*',\(#(\d+),[^;]*\),#(\d+)\);",
        head,
        text,
    )
    app = _find_all(rb"^#(\d+) = APPLICATION_CONTEXT\(", head, text)
    if len(pd) != 1 or len(rep) != 1 or len(app) != 1:
        raise ValueError("not a single-solid STEP file from step_bytes()")
    pd, (rep, origin, ctx), app = int(pd[0]), [int(v) for v in rep[0]], int(app[0])
    nxt = max(ids) + 1

    def new():
        nonlocal nxt
        nxt += 1
        return nxt - 1

    out = []
    dz, dx = new(), new()
    out += [f"#{dz} = DIRECTION('',(0.,0.,1.));", f"#{dx} = DIRECTION('',(1.,0.,0.));"]
    placements = []
    for x, y, z in np.asarray(offsets_mm, np.float64).tolist():
        pt, ax = new(), new()
        out += [
            f"#{pt} = CARTESIAN_POINT('',({x!r},{y!r},{z!r}));",
            f"#{ax} = AXIS2_PLACEMENT_3D('',#{pt},#{dz},#{dx});",
        ]
        placements.append(ax)
    sdr, pds, apd, pdf, prod, pc, pdc, sr, cat = (new() for _ in range(9))
    items = ",".join(f"#{v}" for v in [origin, *placements])
    out += [
        f"#{sdr} = SHAPE_DEFINITION_REPRESENTATION(#{pds},#{sr});",
        f"#{pds} = PRODUCT_DEFINITION_SHAPE('','',#{apd});",
        f"#{apd} = PRODUCT_DEFINITION('design','',#{pdf},#{pdc});",
        f"#{pdf} = PRODUCT_DEFINITION_FORMATION('','',#{prod});",
        f"#{prod} = PRODUCT('{name}','{name}','',(#{pc}));",
        f"#{pc} = PRODUCT_CONTEXT('',#{app},'mechanical');",
        f"#{pdc} = PRODUCT_DEFINITION_CONTEXT('part definition',#{app},'design');",
        f"#{sr} = SHAPE_REPRESENTATION('',({items}),#{ctx});",
        f"#{cat} = PRODUCT_RELATED_PRODUCT_CATEGORY('part',$,(#{prod}));",
    ]
    for n, ax in enumerate(placements):
        cdsr, rr, idt, ps, nauo = (new() for _ in range(5))
        out += [
            f"#{cdsr} = CONTEXT_DEPENDENT_SHAPE_REPRESENTATION(#{rr},#{ps});",
            f"#{rr} = ( REPRESENTATION_RELATIONSHIP('','',#{rep},#{sr}) "
            f"REPRESENTATION_RELATIONSHIP_WITH_TRANSFORMATION(#{idt}) "
            "SHAPE_REPRESENTATION_RELATIONSHIP() );",
            f"#{idt} = ITEM_DEFINED_TRANSFORMATION('','',#{origin},#{ax});",
            f"#{ps} = PRODUCT_DEFINITION_SHAPE('Placement','Placement of an item',#{nauo});",
            f"#{nauo} = NEXT_ASSEMBLY_USAGE_OCCURRENCE('{n + 1}','tile_{n}','',#{apd},#{pd},$);",
        ]
    tail = b"ENDSEC;\nEND-ISO-10303-21;"
    cut = text.rindex(tail)
    body = text[:cut] + ("\n".join(out) + "\n").encode("ascii") + text[cut:]
    return re.sub(rb"FILE_NAME\('[^']*'", f"FILE_NAME('{name}'".encode(), body, count=1)


def _find_all(pattern, head, text):
    """Return the matches of ``pattern`` in ``head``, or in all of ``text`` if none there."""
    found = re.findall(pattern, head, re.M)
    return found or re.findall(pattern, text, re.M)


def check_solid(shape, validate=False):
    """Describe the solids of a build123d shape: count, closed shells, volume.

    Returns
    -------
    dict
        ``solids`` (count), ``closed`` (every shell without free edges),
        ``volume_mm3`` (sum over solids) and, with ``validate``, ``valid``
        (OCCT BRepCheck, slow on large shapes).
    """
    from OCP.ShapeAnalysis import ShapeAnalysis_FreeBounds

    solids = shape.solids()
    closed = len(solids) > 0
    for sh in shape.shells():
        bounds = ShapeAnalysis_FreeBounds(sh.wrapped)
        closed &= _empty(bounds.GetClosedWires()) and _empty(bounds.GetOpenWires())
    out = {
        "solids": len(solids),
        "closed": bool(closed),
        "volume_mm3": float(sum(s.volume for s in solids)),
    }
    if validate:
        from OCP.BRepCheck import BRepCheck_Analyzer

        out["valid"] = bool(BRepCheck_Analyzer(shape.wrapped).IsValid())
    return out


def read_step(path):
    """Import a STEP file as a build123d shape (mm)."""
    from build123d import import_step

    return import_step(str(path))


def _empty(compound):
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer

    return compound.IsNull() or not TopExp_Explorer(compound, TopAbs_EDGE).More()
