"""``camera.json``: the camera a plate was imaged in, and what its active areas collect.

``doefab camera`` writes it beside ``effective_psf.npy`` (:func:`write_camera`); the
PSF checks (:mod:`doe.records.psf_source`) read it (:func:`read_camera`) to refuse
an effective PSF sampled for another sub-pixel grid. The file is a JSON object
(indented, keys sorted) with

- ``settings``: every input of the camera model: ``bandwidth_nm``, ``spectrum``
  (``description``, ``wavelengths_nm``, ``weights``), ``f_number`` (null: the
  square clear aperture), ``stop``, ``stop_diameter_mm``, ``aperture_mm``,
  ``defocus_um`` (> 0: the sensor behind the image plane), ``rotation_deg`` (> 0:
  counter-clockwise as the PSF is viewed), ``kernel_size``, and the model's sampling
  ``margin_subpixels`` and ``supersample``;
- ``collected_fraction``: the sum of E before normalising (the fraction of the
  light through the stop that the K x K active areas collect);
- ``correlation``, ``rmse``: of the effective PSF against the design's PSF
  (``target_psf``, CONVENTIONS.md's figures; correlation null for a uniform one);
- ``window``: the same figures and ``efficiency`` of the monochromatic plate of
  square pixels at the design wavelength (the design's own window powers);
- ``budget`` (with ``--budget``): :func:`doe.camera_budget.camera_budget`: the
  ``nominal`` camera's figures, the ``limit`` (its rmse + the ``allowance``), the
  design ``goals`` and whether the nominal camera meets them, the nominal ``dots``,
  and per setting (``bandwidth_nm``, ``f_number``, ``defocus_um``, ``rotation_deg``,
  in ``axes``) its ``values`` and the ``correlation``, ``rmse`` and
  ``collected_fraction`` of each, varied alone from the default camera, and
  ``within_budget`` (``range`` [lo, hi] within the limit or null, ``ends``, ``why``);
- ``design_dir``, ``kind`` (``fab`` or ``retrieve``), ``target_psf``, ``psf``
  (``effective_psf.npy``), ``seconds``, ``design`` (:func:`doe.derived.design_summary`
  for the tile's N), ``versions``.
"""

from dataclasses import dataclass, field
from pathlib import Path

from doe.infra.files import read_json, write_json

CAMERA_JSON = "camera.json"
EFFECTIVE_PSF = "effective_psf.npy"
CAMERA_FIGURE = "camera.png"
BUDGET_FIGURE = "camera_budget.png"


@dataclass(frozen=True)
class CameraRecord:
    """One ``camera.json``: the values other stages read, and the whole object.

    Fields are as recorded (None when absent), not coerced: the reader decides.
    """

    settings: object = None
    collected_fraction: object = None
    correlation: object = None
    rmse: object = None
    design: object = None
    data: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_dict(cls, obj):
        return cls(
            settings=obj.get("settings"),
            collected_fraction=obj.get("collected_fraction"),
            correlation=obj.get("correlation"),
            rmse=obj.get("rmse"),
            design=obj.get("design"),
            data=obj,
        )


def read_camera(path):
    """Read a ``camera.json`` (InputError naming it when missing, not JSON or no object)."""
    return CameraRecord.from_dict(read_json(Path(path)))


def write_camera(path, record):
    """Write a ``camera.json`` (a :class:`CameraRecord` or its dict), atomically."""
    write_json(path, record.data if isinstance(record, CameraRecord) else record)
