//! Reading and validating a bundle directory.

use std::path::{Path, PathBuf};

use image::{DynamicImage, GrayImage, ImageBuffer, ImageFormat, Luma, RgbImage};
use ndarray::{Array2, Array3, ArrayRef, Dimension, IntoDimension};

use crate::error::{BundleError, Result};
use crate::meta::BundleMeta;
use crate::npy::{read_npy_checked, shape_string};

pub const BUNDLE_JSON: &str = "bundle.json";
pub const TRACKS_DIR: &str = "tracks";
pub const PARTICLES_DIR: &str = "particles";
pub const VIEWS_DIR: &str = "views";

pub const OBJECT_POINTS_FILE: &str = "tracks/object_points.npy";
pub const OBJECT_VISIBILITY_FILE: &str = "tracks/object_visibility.npy";
pub const OBJECT_MOTION_VALID_FILE: &str = "tracks/object_motion_valid.npy";
pub const HAND_POINTS_FILE: &str = "tracks/hand_points.npy";
pub const HAND_VISIBILITY_FILE: &str = "tracks/hand_visibility.npy";
pub const SURFACE_POINTS_FILE: &str = "particles/surface_points.npy";
pub const SURFACE_COLORS_FILE: &str = "particles/surface_colors.npy";
pub const INTERIOR_POINTS_FILE: &str = "particles/interior_points.npy";
pub const INTERIOR_COLORS_FILE: &str = "particles/interior_colors.npy";
/// Where [`crate::BundleWriter::write_mesh_obj`] puts the mesh.
pub const DEFAULT_MESH_FILE: &str = "mesh/object.obj";

/// Depth PNG value per metre.
pub const DEPTH_PNG_UNITS_PER_METRE: f32 = 1000.0;

/// Per-frame tracks in world metres. `T` frames, `N` object points, `M` hand anchors.
#[derive(Debug, Clone, PartialEq)]
pub struct Tracks {
    /// (T, N, 3)
    pub object_points: Array3<f32>,
    /// (T, N): the point is seen by at least one camera in that frame.
    pub object_visibility: Array2<bool>,
    /// (T, N): the position is trustworthy for supervising motion.
    pub object_motion_valid: Array2<bool>,
    /// (T, M, 3)
    pub hand_points: Array3<f32>,
    /// (T, M)
    pub hand_visibility: Array2<bool>,
}

impl Tracks {
    pub fn frame_count(&self) -> usize {
        self.object_points.shape()[0]
    }
    pub fn object_point_count(&self) -> usize {
        self.object_points.shape()[1]
    }
    pub fn hand_anchor_count(&self) -> usize {
        self.hand_points.shape()[1]
    }
}

/// Particles sampling the object in the first frame, world metres, colours RGB in [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub struct FirstFrameParticles {
    /// (Ns, 3)
    pub surface_points: Array2<f32>,
    /// (Ns, 3)
    pub surface_colors: Array2<f32>,
    /// (Ni, 3); Ni may be 0.
    pub interior_points: Array2<f32>,
    /// (Ni, 3)
    pub interior_colors: Array2<f32>,
}

/// The per-frame images stored for each camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ImageKind {
    /// 8-bit RGB.
    Rgb,
    /// 16-bit grey, millimetres, 0 = no measurement.
    Depth,
    /// 8-bit grey, 0 or 255.
    MaskObject,
    /// 8-bit grey, 0 or 255.
    MaskHand,
}

impl ImageKind {
    pub const ALL: [ImageKind; 4] = [
        ImageKind::Rgb,
        ImageKind::Depth,
        ImageKind::MaskObject,
        ImageKind::MaskHand,
    ];

    /// Directory name under `views/<camera>/`.
    pub fn dir_name(self) -> &'static str {
        match self {
            ImageKind::Rgb => "rgb",
            ImageKind::Depth => "depth",
            ImageKind::MaskObject => "mask_object",
            ImageKind::MaskHand => "mask_hand",
        }
    }

    fn colour_type(self) -> image::ColorType {
        match self {
            ImageKind::Rgb => image::ColorType::Rgb8,
            ImageKind::Depth => image::ColorType::L16,
            ImageKind::MaskObject | ImageKind::MaskHand => image::ColorType::L8,
        }
    }
}

/// Which segmentation mask to load.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MaskKind {
    Object,
    Hand,
}

impl From<MaskKind> for ImageKind {
    fn from(kind: MaskKind) -> Self {
        match kind {
            MaskKind::Object => ImageKind::MaskObject,
            MaskKind::Hand => ImageKind::MaskHand,
        }
    }
}

/// File name of a frame's image: five-digit zero-padded index.
pub fn frame_file_name(frame: usize) -> String {
    format!("{frame:05}.png")
}

/// Bounding box (min, max corners, pixel edges) of a mask's set pixels
/// (above 127).
pub fn mask_box(mask: &GrayImage) -> Option<([f64; 2], [f64; 2])> {
    let mut bounds: Option<([u32; 2], [u32; 2])> = None;
    for (x, y, pixel) in mask.enumerate_pixels() {
        if pixel.0[0] > 127 {
            let (min, max) = bounds.get_or_insert(([x, y], [x, y]));
            *min = [min[0].min(x), min[1].min(y)];
            *max = [max[0].max(x), max[1].max(y)];
        }
    }
    bounds.map(|(min, max)| {
        (
            [f64::from(min[0]), f64::from(min[1])],
            [f64::from(max[0] + 1), f64::from(max[1] + 1)],
        )
    })
}

/// A validated bundle: metadata and arrays in memory, images loaded on demand.
#[derive(Debug, Clone)]
pub struct Bundle {
    pub root: PathBuf,
    pub meta: BundleMeta,
    pub tracks: Tracks,
    pub particles: FirstFrameParticles,
}

impl Bundle {
    /// Reads `bundle.json` and all arrays under `dir` and validates them
    /// (everything except images; see [`Bundle::validate_images`]).
    pub fn open(dir: impl AsRef<Path>) -> Result<Bundle> {
        let root = dir.as_ref().to_path_buf();
        if !root.is_dir() {
            let problem = if root.exists() {
                "not a directory (a bundle is a folder holding bundle.json)"
            } else {
                "no such folder"
            };
            return Err(BundleError::new(&root, crate::error::IO_FIELD, problem));
        }
        let json_path = root.join(BUNDLE_JSON);
        let meta = BundleMeta::read(&json_path)?;
        meta.validate(&json_path)?;

        let tracks = read_tracks(&root, &meta)?;
        meta.validate_hand_ranges(&json_path, tracks.hand_anchor_count())?;
        let particles = read_particles(&root)?;
        if let Some(mesh) = &meta.mesh {
            let mesh_path = root.join(mesh);
            if !mesh_path.is_file() {
                return Err(BundleError::new(
                    &json_path,
                    "mesh",
                    format!("names {} which is not a file", mesh_path.display()),
                ));
            }
        }
        Ok(Bundle {
            root,
            meta,
            tracks,
            particles,
        })
    }

    pub fn frame_count(&self) -> usize {
        self.meta.frame_count
    }

    /// Path of one frame image; errors on an unknown camera or frame.
    pub fn image_path(&self, cam_index: usize, frame: usize, kind: ImageKind) -> Result<PathBuf> {
        image_path(&self.root, &self.meta, cam_index, frame, kind)
    }

    /// Checks every image of every camera and frame: present, decodable PNG,
    /// camera size, expected colour type, masks holding only 0 and 255.
    /// Stops at the first problem.
    pub fn validate_images(&self) -> Result<()> {
        for cam_index in 0..self.meta.cameras.len() {
            for frame in 0..self.meta.frame_count {
                for kind in ImageKind::ALL {
                    let image = self.load_image(cam_index, frame, kind)?;
                    if let DynamicImage::ImageLuma8(mask) = &image
                        && let Some((x, y, value)) = mask
                            .enumerate_pixels()
                            .find(|(_, _, p)| !matches!(p.0[0], 0 | 255))
                    {
                        let path = self.image_path(cam_index, frame, kind)?;
                        return Err(BundleError::new(
                            path,
                            format!("pixel[{x},{y}]"),
                            format!("mask value {} is neither 0 nor 255", value.0[0]),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    pub fn load_rgb(&self, cam_index: usize, frame: usize) -> Result<RgbImage> {
        match self.load_image(cam_index, frame, ImageKind::Rgb)? {
            DynamicImage::ImageRgb8(image) => Ok(image),
            other => Err(self.unexpected_colour(cam_index, frame, ImageKind::Rgb, &other)),
        }
    }

    /// Raw depth PNG in millimetres, 0 = no measurement.
    pub fn load_depth_mm(
        &self,
        cam_index: usize,
        frame: usize,
    ) -> Result<ImageBuffer<Luma<u16>, Vec<u16>>> {
        match self.load_image(cam_index, frame, ImageKind::Depth)? {
            DynamicImage::ImageLuma16(image) => Ok(image),
            other => Err(self.unexpected_colour(cam_index, frame, ImageKind::Depth, &other)),
        }
    }

    /// Depth in metres, row-major `width * height`, NaN where there is no measurement.
    pub fn load_depth_m(&self, cam_index: usize, frame: usize) -> Result<Vec<f32>> {
        let depth_mm = self.load_depth_mm(cam_index, frame)?;
        Ok(depth_mm
            .as_raw()
            .iter()
            .map(|&mm| {
                if mm == 0 {
                    f32::NAN
                } else {
                    f32::from(mm) / DEPTH_PNG_UNITS_PER_METRE
                }
            })
            .collect())
    }

    pub fn load_mask(&self, cam_index: usize, frame: usize, kind: MaskKind) -> Result<GrayImage> {
        let kind = ImageKind::from(kind);
        match self.load_image(cam_index, frame, kind)? {
            DynamicImage::ImageLuma8(image) => Ok(image),
            other => Err(self.unexpected_colour(cam_index, frame, kind, &other)),
        }
    }

    /// Decodes one image and checks its size and colour type.
    fn load_image(&self, cam_index: usize, frame: usize, kind: ImageKind) -> Result<DynamicImage> {
        let path = self.image_path(cam_index, frame, kind)?;
        let bytes = std::fs::read(&path).map_err(|e| BundleError::io(&path, "reading", &e))?;
        let image = image::load_from_memory_with_format(&bytes, ImageFormat::Png)
            .map_err(|e| BundleError::new(&path, "png", format!("cannot decode: {e}")))?;
        if image.color() != kind.colour_type() {
            return Err(self.unexpected_colour(cam_index, frame, kind, &image));
        }
        let camera = &self.meta.cameras[cam_index];
        if (image.width(), image.height()) != (camera.width, camera.height) {
            return Err(BundleError::new(
                &path,
                "size",
                format!(
                    "expected {}x{} (cameras[{cam_index}] \"{}\"), found {}x{}",
                    camera.width,
                    camera.height,
                    camera.name,
                    image.width(),
                    image.height()
                ),
            ));
        }
        Ok(image)
    }

    fn unexpected_colour(
        &self,
        cam_index: usize,
        frame: usize,
        kind: ImageKind,
        image: &DynamicImage,
    ) -> BundleError {
        let path = self
            .image_path(cam_index, frame, kind)
            .unwrap_or_else(|e| e.path);
        BundleError::new(
            path,
            "colour_type",
            format!(
                "expected {:?}, found {:?}",
                kind.colour_type(),
                image.color()
            ),
        )
    }
}

pub(crate) fn image_path(
    root: &Path,
    meta: &BundleMeta,
    cam_index: usize,
    frame: usize,
    kind: ImageKind,
) -> Result<PathBuf> {
    let json_path = root.join(BUNDLE_JSON);
    let camera = meta.cameras.get(cam_index).ok_or_else(|| {
        BundleError::new(
            &json_path,
            "cameras",
            format!(
                "camera index {cam_index} out of range ({} cameras)",
                meta.cameras.len()
            ),
        )
    })?;
    if frame >= meta.frame_count {
        return Err(BundleError::new(
            &json_path,
            "frame_count",
            format!("frame {frame} out of range ({} frames)", meta.frame_count),
        ));
    }
    Ok(root
        .join(VIEWS_DIR)
        .join(&camera.name)
        .join(kind.dir_name())
        .join(frame_file_name(frame)))
}

fn check_shape(path: &Path, found: &[usize], expected: &[usize], why: &str) -> Result<()> {
    if found == expected {
        return Ok(());
    }
    Err(BundleError::new(
        path,
        "shape",
        format!(
            "expected {} ({why}), found {}",
            shape_string(expected),
            shape_string(found)
        ),
    ))
}

/// Rejects NaN/inf; the field names the element, e.g. `object_points[12,3,1]`.
fn check_finite<D: Dimension>(path: &Path, name: &str, array: &ArrayRef<f32, D>) -> Result<()> {
    match array.indexed_iter().find(|(_, v)| !v.is_finite()) {
        None => Ok(()),
        Some((index, value)) => Err(BundleError::new(
            path,
            format!("{name}[{}]", index_string(index.into_dimension().slice())),
            format!("value {value} is not finite"),
        )),
    }
}

fn check_unit_interval(path: &Path, name: &str, array: &Array2<f32>) -> Result<()> {
    match array
        .indexed_iter()
        .find(|(_, v)| !(0.0..=1.0).contains(*v))
    {
        None => Ok(()),
        Some(((row, col), value)) => Err(BundleError::new(
            path,
            format!("{name}[{row},{col}]"),
            format!("colour {value} is outside [0, 1]"),
        )),
    }
}

fn index_string(index: &[usize]) -> String {
    index
        .iter()
        .map(usize::to_string)
        .collect::<Vec<_>>()
        .join(",")
}

fn file_stem_name(relative: &str) -> &str {
    relative
        .rsplit('/')
        .next()
        .and_then(|f| f.strip_suffix(".npy"))
        .unwrap_or(relative)
}

fn read_tracks(root: &Path, meta: &BundleMeta) -> Result<Tracks> {
    let t = meta.frame_count;
    let points_path = root.join(OBJECT_POINTS_FILE);
    let object_points: Array3<f32> = read_npy_checked(&points_path)?;
    let n = object_points.shape()[1];
    check_shape(
        &points_path,
        object_points.shape(),
        &[t, n, 3],
        "T from bundle.json frame_count, N, 3",
    )?;
    if n == 0 {
        return Err(BundleError::new(
            &points_path,
            "shape",
            "N must be >= 1 (no tracked object points)",
        ));
    }

    let hand_path = root.join(HAND_POINTS_FILE);
    let hand_points: Array3<f32> = read_npy_checked(&hand_path)?;
    let m = hand_points.shape()[1];
    check_shape(
        &hand_path,
        hand_points.shape(),
        &[t, m, 3],
        "T from bundle.json frame_count, M, 3",
    )?;

    let read_mask = |relative: &str, cols: usize, why: &str| -> Result<Array2<bool>> {
        let path = root.join(relative);
        let mask: Array2<bool> = read_npy_checked(&path)?;
        check_shape(&path, mask.shape(), &[t, cols], why)?;
        Ok(mask)
    };
    let object_visibility = read_mask(OBJECT_VISIBILITY_FILE, n, "T, N as in object_points.npy")?;
    let object_motion_valid =
        read_mask(OBJECT_MOTION_VALID_FILE, n, "T, N as in object_points.npy")?;
    let hand_visibility = read_mask(HAND_VISIBILITY_FILE, m, "T, M as in hand_points.npy")?;

    check_finite(
        &points_path,
        file_stem_name(OBJECT_POINTS_FILE),
        &object_points,
    )?;
    check_finite(&hand_path, file_stem_name(HAND_POINTS_FILE), &hand_points)?;
    Ok(Tracks {
        object_points,
        object_visibility,
        object_motion_valid,
        hand_points,
        hand_visibility,
    })
}

fn read_particles(root: &Path) -> Result<FirstFrameParticles> {
    let read_pair =
        |points_file: &str, colors_file: &str, allow_empty: bool| -> Result<[Array2<f32>; 2]> {
            let points_path = root.join(points_file);
            let points: Array2<f32> = read_npy_checked(&points_path)?;
            let count = points.shape()[0];
            check_shape(&points_path, points.shape(), &[count, 3], "count, 3")?;
            if count == 0 && !allow_empty {
                return Err(BundleError::new(
                    &points_path,
                    "shape",
                    "at least one particle is required",
                ));
            }
            check_finite(&points_path, file_stem_name(points_file), &points)?;

            let colors_path = root.join(colors_file);
            let colors: Array2<f32> = read_npy_checked(&colors_path)?;
            check_shape(
                &colors_path,
                colors.shape(),
                &[count, 3],
                &format!("one RGB row per row of {points_file}"),
            )?;
            check_unit_interval(&colors_path, file_stem_name(colors_file), &colors)?;
            Ok([points, colors])
        };
    let [surface_points, surface_colors] =
        read_pair(SURFACE_POINTS_FILE, SURFACE_COLORS_FILE, false)?;
    let [interior_points, interior_colors] =
        read_pair(INTERIOR_POINTS_FILE, INTERIOR_COLORS_FILE, true)?;
    Ok(FirstFrameParticles {
        surface_points,
        surface_colors,
        interior_points,
        interior_colors,
    })
}
