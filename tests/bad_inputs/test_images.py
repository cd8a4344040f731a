"""Camera images: missing, truncated or undecodable files (in the main process and in data workers), PNG and EXIF
images, PIL and tensor images of other pixel types, one image given for two cameras.

Each row runs on the tiny synthetic world of tests/conftest.py and a random tiny model (bad_inputs/conftest.py).
"""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest
import torch

from bad_inputs.support import (
    add,
    av2_copy,
    av2_error,
    break_image,
    camera_record,
    evaluate_world,
    forbid,
    mapper_frame,
    rig_files,
    row,
    table,
    val_dataset,
)
from instagram_hdmap.config import UserError, load_config


def _worker_image_row(how: str):
    def run(env):
        root = env.shadow_world(copy_samples=True)
        path = break_image(root, root, 1, "CAM_BACK_RIGHT", how)
        line = env.error(rf"{re.escape(path.name)}", "evaluate", env.yaml, f"data.dataroot={root}",
                         "data.num_workers=1", "--checkpoint", env.ckpt, "--out", env.tmp / "e")
        assert "worker" not in line.lower()

    return run


for _how in ("missing", "truncated", "undecodable"):
    add(f"{_how}_image_with_a_worker", f"a {_how} image with data.num_workers=1: one line", _worker_image_row(_how))


@row("Mapper: a float image on 0..255, with NaN, or normalised already is named (was silently wrong)")
def row_mapper_float_images(env):
    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    mapper(images={c: v.astype(np.float32) / 255 for c, v in images.items()}, intrinsics=K, cam_to_ego=poses)  # fine
    for image in (images["CAM_FRONT"].astype(np.float32),  # 0..255
                  np.full(images["CAM_FRONT"].shape, np.nan, np.float32),
                  (images["CAM_FRONT"] / 255.0 - 0.45) / 0.225,  # normalised already
                  torch.from_numpy(images["CAM_FRONT"]).permute(2, 0, 1).float()):  # a tensor on 0..255
        with pytest.raises(RigError, match=r"camera CAM_FRONT: .*(0\.\.1|NaN)"):
            mapper(images={**images, "CAM_FRONT": image}, intrinsics=K, cam_to_ego=poses)


@row("predict-images: the same image for two cameras is named")
def row_same_image_for_two_cameras(env):
    path, images = rig_files(env)
    images[4] = images[1]
    env.error(r"cameras CAM_FRONT and CAM_BACK are given the same image", "predict-images", "--checkpoint",
              env.ckpt, "--rig", path, "--out", env.tmp / "out", "--device", "cpu", *images)


@row("Mapper: a PIL image of 16-bit or float pixels is named (convert('RGB') made it all white or all black)")
def row_mapper_pil_16bit_and_float(env):
    from PIL import Image

    from instagram_hdmap.data.rig import RigError

    mapper, images, K, poses = mapper_frame(env)
    gray = images["CAM_FRONT"][..., 0]
    for image in (Image.fromarray(gray.astype(np.uint16) * 256), Image.fromarray(gray.astype(np.float32) / 255)):
        with pytest.raises(RigError, match=rf"camera CAM_FRONT: a PIL image of mode '{re.escape(image.mode)}' .* "
                                           r"clipped to 8 bits"):
            mapper(images={**images, "CAM_FRONT": image}, intrinsics=K, cam_to_ego=poses)
    mapper(images={**images, "CAM_FRONT": Image.fromarray(gray)}, intrinsics=K, cam_to_ego=poses)  # 8-bit gray: fine


@row("Mapper / predict-images: PNG frames whose size is not a multiple of the decode factor run (refused: "
          "'decodes to 200x112 at 1/8, expected 200x113': OpenCV shrinks a PNG to floor(W / f), a JPEG to ceil)")
def row_png_frames(env):
    from PIL import Image

    from instagram_hdmap import Frame
    from instagram_hdmap.data.rig import rig

    mapper, _, _, poses = mapper_frame(env)
    sensors = rig((1600, 900))  # nuScenes' size; the tiny model's 64 x 160 images decode a JPEG at 1/8
    v, u = np.mgrid[:900, :1600]
    arrays = {c: np.stack([(u + 40 * k) % 256, v % 256, (u + v) % 256], -1).astype(np.uint8)
              for k, c in enumerate(mapper.cameras)}
    paths = {}
    for c, a in arrays.items():
        paths[c] = env.tmp / f"{c}.png"
        Image.fromarray(a).save(paths[c])
    K = {c: sensors[c].intrinsic for c in mapper.cameras}
    from_files = mapper.batch([Frame(images=paths, intrinsics=K, cam_to_ego=poses)])
    in_memory = mapper.batch([Frame(images=arrays, intrinsics=K, cam_to_ego=poses)])
    for key in ("images", "post_rot", "post_tran"):  # the PNG decoded whole: the same pixels as the arrays
        torch.testing.assert_close(from_files[key], in_memory[key])


@row("nuScenes tables: two cameras of a sample reading the same image file is named (ran, exit 0)")
def row_dataset_same_image_for_two_cameras(env):
    def same(tables):
        front, _ = camera_record(tables, "CAM_FRONT")
        left, _ = camera_record(tables, "CAM_FRONT_LEFT")
        left["filename"] = front["filename"]

    evaluate_world(env, same, r"cameras CAM_FRONT_LEFT and CAM_FRONT read the same image file .*CAM_FRONT__")


@row("Mapper: an image tensor in bfloat16 (0..1, a mixed-precision pipeline's) crashed with torch's raw "
            "'TypeError: Got unsupported ScalarType BFloat16' (float16 and float64 tensors were accepted)")
def row_mapper_bfloat16_image(env):
    from instagram_hdmap import Frame, Mapper
    from instagram_hdmap.data.rig import rig

    mapper = Mapper.from_checkpoint(env.ckpt, device="cpu")
    calib = rig((64, 36))
    poses = {c: np.vstack([np.c_[calib[c].rot, calib[c].trans], [0, 0, 0, 1]]) for c in mapper.cameras}
    intrinsics = {c: calib[c].intrinsic for c in mapper.cameras}
    pixels = torch.rand(3, 36, 64, generator=torch.Generator().manual_seed(0)).to(torch.bfloat16)
    got = mapper.batch([Frame({c: pixels for c in mapper.cameras}, intrinsics, poses)])["images"]
    want = mapper.batch([Frame({c: pixels.float() for c in mapper.cameras}, intrinsics, poses)])["images"]
    assert torch.equal(got, want)


@row("a dataset whose camera images were resized (a half-resolution copy of nuScenes) or rotated was refused "
            "as 'decodes to 100x57 at 1/2, expected 200x113 from its recorded size 400x225', reduced-decode sizes "
            "that name neither the file's size nor what to do; the line says both")
def row_resized_dataset_images_named(env):
    from PIL import Image

    root = env.shadow_world(copy_samples=True)
    for image in (root / "samples" / "CAM_FRONT").iterdir():
        with Image.open(image) as im:
            size = im.size
            im.resize((size[0] // 2, size[1] // 2)).save(image)
    env.error(rf"the file is {size[0] // 2}x{size[1] // 2}, a resized or rotated copy\? .*use the dataset's original "
              "images", "evaluate", env.yaml, f"data.dataroot={root}", "--checkpoint", env.ckpt, "--out", env.tmp / "e")


@row("a camera JPEG carrying an EXIF orientation tag (a phone or an editor: 3, rotated 180 degrees) was "
            "decoded turned by OpenCV while its calibration and size check read the stored pixels: the model saw "
            "the image upside down, exit 0 (a 90-degree tag was blamed on 'a resized or rotated copy'); the tag is "
            "named, in the Mapper (predict-images) and in a dataset")
def row_exif_orientation(env):
    from PIL import Image

    from instagram_hdmap.data.transforms import ImageError, read_image

    src = next((env.world / "samples" / "CAM_FRONT").glob("*.jpg"))
    for tag, what in ((3, "rotated 180 degrees"), (6, "rotated 90 degrees")):
        exif = Image.Exif()
        exif[0x0112] = tag
        path = env.tmp / f"tag{tag}.jpg"
        with Image.open(src) as im:
            im.save(path, quality=95, exif=exif)
        with pytest.raises(ImageError, match=rf"carries the EXIF orientation tag {tag} \({what}\)"):
            read_image(path, 2)
    exif = Image.Exif()
    exif[0x0112] = 1  # the normal orientation (and a tag-less image, the datasets' own) decode as before
    with Image.open(src) as im:
        im.save(env.tmp / "tag1.jpg", quality=95, exif=exif)
    assert read_image(env.tmp / "tag1.jpg", 2)[0].shape == read_image(src, 2)[0].shape
    # a dataset copy whose camera images were re-saved with the tag: the sample names it
    world = env.shadow_world(copy_samples=True)
    for image in (world / "samples" / "CAM_BACK").glob("*.jpg"):
        exif = Image.Exif()
        exif[0x0112] = 3
        with Image.open(image) as im:
            im.load()
            im.save(image, quality=95, exif=exif)
    cfg = load_config(env.yaml, [f"data.dataroot={world}"])
    with pytest.raises(UserError, match="EXIF orientation tag 3"):
        val_dataset(cfg)[0]


@row("predict-images: a rig file's image_size written as floats ([400.0, 225.0], numpy's or MATLAB's JSON) was "
            "refused as not 'positive whole numbers'; an image OpenCV cannot read (a float TIFF, an animated GIF) was "
            "'corrupt or not an image'")
def row_rig_float_size_and_unreadable_image_kinds(env):
    from PIL import Image

    from instagram_hdmap.data.transforms import ImageError, read_image

    rig, images = rig_files(env, lambda d: d.update(image_size=[400.0, 225.0]))
    rc, _, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "out",
                         "--device", "cpu", *images)
    assert rc == 0, err[-2000:]
    env.error(r"'image_size' must be \[width, height\] .* got \[400\.5, 225\]", "predict-images", "--checkpoint",
              env.ckpt, "--rig", rig_files(env, lambda d: d.update(image_size=[400.5, 225]))[0], "--out",
              env.tmp / "out2", "--device", "cpu", *images)
    tif = env.tmp / "float.tif"
    Image.fromarray(np.full((225, 400), 0.5, np.float32), mode="F").save(tif)
    with pytest.raises(ImageError, match=r"cannot be decoded \(a TIFF F image, which OpenCV does not read; save it as "
                                         r"an 8-bit RGB JPEG or PNG\)"):
        read_image(tif)
    junk = env.tmp / "junk.jpg"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(ImageError, match=r"corrupt or not an image"):
        read_image(junk)


@row("predict-images: a byte-identical copy of one camera's image given for another camera (CAM_FRONT.jpg "
            "copied to fill CAM_FRONT_RIGHT) ran, exit 0 (the same path twice, or a link to it, was named)")
def row_predict_images_copy_of_an_image(env):
    rig, images = rig_files(env)
    shutil.copy(images[1], images[2])
    forbid(env, "instagram_hdmap.predict.save_figure", "drawing")
    env.error(r"cameras CAM_FRONT and CAM_FRONT_RIGHT are given the same image: .*CAM_FRONT_RIGHT\.jpg is a copy of "
              r".*CAM_FRONT\.jpg \(the same bytes\)", "predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out",
              env.tmp / "out", "--device", "cpu", *images)


@row("predict-images: one image for two cameras (the same file or a copy) was refused even where it is a blank "
            "frame, the image a failed camera gives (the model trains with such cameras: data.camera_dropout), so a "
            "frame with two failed cameras could not be run at all; a one-colour image may stand for several")
def row_predict_images_blank_frames_may_repeat(env):
    import cv2

    rig, images = rig_files(env)
    black = env.tmp / "black.png"
    cv2.imwrite(str(black), np.zeros((225, 400, 3), np.uint8))
    for a, b in ((1, 2), (3, 4)):
        shutil.copy(black, images[a])
        shutil.copy(black, images[b])
    rc, _, err = env.cli("predict-images", "--checkpoint", env.ckpt, "--rig", rig, "--out", env.tmp / "blank",
                         "--device", "cpu", images[0], images[1], images[2], black, black, *images[5:])
    assert rc == 0, err[-2000:]


@row("AV2: a camera folder of <timestamp_ns>.JPG images was 'the folder holds no images; the log's camera and "
            "lidar timestamps do not match' (both wrong); it names the .JPG files and says to rename them. A log with "
            "no sensors/cameras at all (the real log of shared/av2_real) was told to choose cameras with "
            "data.av2_cameras; it says the log has no images and that export-gt needs none. A root one level up "
            "(ROOT/sensor/train, as s5cmd copies the bucket) names the subfolder, and a renamed log folder (every map "
            "file naming another log) is said to be one")
def row_av2_camera_images_upper_case_or_absent(env):
    root, log = av2_copy(env)
    for image in (log / "sensors" / "cameras" / "ring_side_left").iterdir():
        image.rename(image.with_suffix(".JPG"))
    up = env.tmp / "up"
    up.mkdir()
    (up / "sensor").symlink_to(root)  # s5cmd's copy of the bucket's av2/sensor/ folder
    av2_error(env, up, r"its folders: sensor .*; its subfolder \S+up/sensor holds the split folder 'train': "
                        r"data\.dataroot=\S+up/sensor")
    line = av2_error(env, root, r"ring_side_left: the folder holds no \.jpg images .*\.JPG files: rename them")
    assert "timestamps do not match" not in line
    cameras = log / "sensors" / "cameras"
    shutil.rmtree(cameras)
    cameras.symlink_to(env.tmp / "unmounted")
    av2_error(env, root, r"sensors/cameras is a symbolic link to \S+unmounted, which does not exist")
    cameras.unlink()
    for other in sorted((root / "train").iterdir()):
        shutil.rmtree(other / "sensors" / "cameras", ignore_errors=True)
    av2_error(env, root, r"sensors/cameras does not exist: the log has no camera images at all .*export-gt does not")
    rc, out, err = env.cli("export-gt", env.yaml, "data.dataset=av2", "data.splits_file=null", f"data.dataroot={root}",
                           "--split", "train", "--out", env.tmp / "gt.json")
    assert rc == 0, err[-2000:]
    log.rename(log.with_name("0" * 8 + log.name[8:]))  # a log folder renamed: its map files name the old id
    av2_error(env, root, r"is the map file of another log .*or the log folder was renamed: all its map files name "
                          r"log ")


@pytest.mark.parametrize("case", table(__name__), ids=str)
def test_images(case, env):
    case.run(env)
