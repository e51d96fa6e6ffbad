"""Pages of an image file, for the readers of captures (fab) and frames (psf_learn)."""


def has_more_pages(inp):
    """Whether an open OpenImageIO ImageInput holds images after its first.

    Reduced-resolution copies of it (TIFF subfile type 1: the thumbnail some
    camera software writes) do not count; they are not another capture. Leaves
    ``inp`` on one of its later subimages.
    """
    page = 1
    while inp.seek_subimage(page, 0):
        if inp.spec().get_int_attribute("tiff:subfiletype", 0) & 1 == 0:
            return True
        page += 1
    return False
