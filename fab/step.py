"""STEP (B-rep) model of a relief tile and of the tiled aperture, via build123d / OCCT.

The tile becomes ONE closed solid whose planar faces are exactly the polygons of
``fab.mesh.relief_surface`` (pixel tops, walls, back face). Their edges are made
once and shared by both adjacent faces, so the shell is closed by construction:
no sewing, no boolean fusion (one box per pixel fused would take hours). The
aperture is an assembly of located instances of that one solid.

Units are millimetres; the STEP header carries a fixed timestamp so a rerun
writes identical bytes. build123d (and OCP) are imported inside the functions.
"""

import io

import numpy as np

from fab.mesh import relief_surface, surface_points_mm

STEP_TIMESTAMP = "2000-01-01T00:00:00"
# A random 8-level tile of N = 175 gives ~80k faces, which builds and writes in about a
# minute on two cores; beyond this count the B-rep route is refused (use the meshes).
MAX_STEP_FACES = 250_000


def step_face_count(levels):
    """Return the number of planar faces the STEP solid of ``levels`` will have."""
    lev = np.asarray(levels, np.int64)
    walls = int((np.diff(lev, axis=1) != 0).sum() + (np.diff(lev, axis=0) != 0).sum())
    return lev.size + walls + 2 * (lev.shape[0] + lev.shape[1]) + 1


def tile_solid(relief):
    """Build the relief tile as one closed build123d ``Solid`` in millimetres."""
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

    surface = relief_surface(relief.levels)
    pts = surface_points_mm(surface, relief).tolist()
    vertices = [BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex() for p in pts]
    edges = {}
    builder = BRep_Builder()
    shell = TopoDS_Shell()
    builder.MakeShell(shell)
    for loop, normal in zip(surface.loops, surface.loop_normals.tolist(), strict=True):
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
    name : str
        Product name of the tile.
    """
    from OCP.APIHeaderSection import APIHeaderSection_MakeHeader
    from OCP.gp import gp_Trsf, gp_Vec
    from OCP.IFSelect import IFSelect_ReturnStatus
    from OCP.Interface import Interface_Static
    from OCP.Message import Message, Message_Gravity
    from OCP.STEPCAFControl import STEPCAFControl_Controller, STEPCAFControl_Writer
    from OCP.STEPControl import STEPControl_Controller, STEPControl_StepModelType
    from OCP.TCollection import TCollection_ExtendedString, TCollection_HAsciiString
    from OCP.TDataStd import TDataStd_Name
    from OCP.TDocStd import TDocStd_Document
    from OCP.TopLoc import TopLoc_Location
    from OCP.XCAFApp import XCAFApp_Application
    from OCP.XCAFDoc import XCAFDoc_DocumentTool
    from OCP.XSControl import XSControl_WorkSession

    doc = TDocStd_Document(TCollection_ExtendedString("XmlOcaf"))
    app = XCAFApp_Application.GetApplication_s()
    app.NewDocument(TCollection_ExtendedString("MDTV-XCAF"), doc)
    app.InitDocument(doc)
    XCAFDoc_DocumentTool.SetLengthUnit_s(doc, 1e-3)  # document unit: mm
    tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    tool.SetAutoNaming_s(False)
    tile = tool.AddShape(solid.wrapped, False)
    TDataStd_Name.Set_s(tile, TCollection_ExtendedString(name))
    if offsets_mm is not None:
        assembly = tool.NewShape()
        TDataStd_Name.Set_s(assembly, TCollection_ExtendedString("aperture"))
        for n, (x, y, z) in enumerate(np.asarray(offsets_mm, np.float64).tolist()):
            trsf = gp_Trsf()
            trsf.SetTranslation(gp_Vec(x, y, z))
            comp = tool.AddComponent(assembly, tile, TopLoc_Location(trsf))
            TDataStd_Name.Set_s(comp, TCollection_ExtendedString(f"{name}_{n}"))
        tool.UpdateAssemblies()

    for printer in Message.DefaultMessenger_s().Printers():
        printer.SetTraceLevel(Message_Gravity.Message_Fail)
    STEPCAFControl_Controller.Init_s()
    STEPControl_Controller.Init_s()
    writer = STEPCAFControl_Writer(XSControl_WorkSession(), False)
    writer.SetNameMode(True)
    header = APIHeaderSection_MakeHeader(writer.Writer().Model())
    if not header.IsDone():
        header = APIHeaderSection_MakeHeader(0)
        header.Apply(writer.Writer().Model())
    header.SetName(TCollection_HAsciiString(name if offsets_mm is None else "aperture"))
    header.SetTimeStamp(TCollection_HAsciiString(STEP_TIMESTAMP))
    header.SetOriginatingSystem(TCollection_HAsciiString("doefab (build123d/OCCT)"))
    Interface_Static.SetIVal_s("write.surfacecurve.mode", 0)  # no pcurves: planar faces only
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    writer.Transfer(doc, STEPControl_StepModelType.STEPControl_AsIs)
    buf = io.BytesIO()
    if writer.WriteStream(buf) != IFSelect_ReturnStatus.IFSelect_RetDone:
        raise RuntimeError("OCCT failed to write the STEP file")
    return buf.getvalue()


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
