"""Re-create Resources/SampleData/lumbar_spine_3mm from the TotalSegmentator example CT.

Usage: python Resources/SampleData/make_sample.py SOURCE_FOLDER
SOURCE_FOLDER holds ct.nrrd and bones_labels.nrrd converted from TotalSegmentator's
tests/reference_files/example_ct.nii.gz and example_seg_fast_force_split.nii.gz (see
lumbar_spine_3mm/PROVENANCE.md). The crop keeps the original geometry (origin, spacing,
direction) because sitk.RegionOfInterest moves only the origin to the first kept voxel.
"""

import os
import sys

import numpy as np
import SimpleITK as sitk

KEEP = {29: "vertebrae_L3", 28: "vertebrae_L4"}
MARGIN_VOXELS = 6  # 18 mm at 3 mm: above the pipeline's 5 mm crop margin, keeps the discs in view


def main(source: str, out_dir: str) -> None:
    ct = sitk.ReadImage(os.path.join(source, "ct.nrrd"))
    labels = sitk.ReadImage(os.path.join(source, "bones_labels.nrrd"))
    array = sitk.GetArrayFromImage(labels)
    z, y, x = np.nonzero(np.isin(array, list(KEEP)))
    size = np.array(ct.GetSize())
    lo = np.maximum(np.array([x.min(), y.min(), z.min()]) - MARGIN_VOXELS, 0)
    hi = np.minimum(np.array([x.max(), y.max(), z.max()]) + MARGIN_VOXELS, size - 1)
    extent = [int(v) for v in hi - lo + 1]
    start = [int(v) for v in lo]
    ct_crop = sitk.Cast(sitk.RegionOfInterest(ct, extent, start), sitk.sitkInt16)
    lab_crop = sitk.RegionOfInterest(labels, extent, start)
    lab_array = sitk.GetArrayFromImage(lab_crop)
    kept = np.where(np.isin(lab_array, list(KEEP)), lab_array, 0).astype(np.uint8)
    lab_out = sitk.GetImageFromArray(kept)
    lab_out.CopyInformation(lab_crop)
    os.makedirs(out_dir, exist_ok=True)
    sitk.WriteImage(ct_crop, os.path.join(out_dir, "ct.nrrd"), True)
    sitk.WriteImage(lab_out, os.path.join(out_dir, "labels.nrrd"), True)
    with open(os.path.join(out_dir, "labels.csv"), "w", encoding="utf-8", newline="") as f:
        f.write("value,name,voxels,volume_ml\n")
        voxel_ml = float(np.prod(ct.GetSpacing())) / 1000.0
        for value, name in sorted(KEEP.items()):
            n = int((kept == value).sum())
            f.write(f"{value},{name},{n},{n * voxel_ml:.1f}\n")
    print("crop start (i, j, k):", start, "size:", extent)
    print("origin:", ct_crop.GetOrigin(), "spacing:", ct_crop.GetSpacing())
    print("direction:", ct_crop.GetDirection())


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1], os.path.join(os.path.dirname(os.path.abspath(__file__)), "lumbar_spine_3mm"))
