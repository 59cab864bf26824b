//! Geometry exports of one frame (PLY marker clouds and meshes) and what the figures of
//! [`gelstereo_io::figures`] are drawn from (overlay markers, captions, the contact surface).

use std::path::Path;

use gelstereo_core::{FrameSummary, GridShape, Point2};
use gelstereo_io::figures::{self, OverlayMarker};
use gelstereo_io::ply::{
    CoordinateFrame, MarkerPoint, TriangleMesh, VertexProperty, write_marker_cloud, write_mesh,
};
use gelstereo_tracking::{ContactFrame, TrackFrame};

use crate::Result;

/// A dense height map of the deformed surface in the gel frame.
pub struct HeightMap {
    /// Rows and columns of samples.
    pub rows: usize,
    /// Columns of samples.
    pub cols: usize,
    /// Sample spacing on the rest surface, mm.
    pub pixel_mm: f64,
    /// Gel-frame `[x, y]` of sample (0, 0), mm.
    pub origin_mm: [f64; 2],
    /// `z` of the deformed surface, mm, row-major (NaN unknown).
    pub z_mm: Vec<f32>,
}

/// The deformed surface's height in the gel frame, sampled `per_pitch` times per marker pitch over
/// the lattice's rest positions: each marker's `z`, bilinear within each lattice cell whose four
/// markers are known.
pub fn height_map(
    shape: GridShape,
    contact: &ContactFrame,
    gel: &crate::GelFrame,
    per_pitch: usize,
) -> HeightMap {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let z: Vec<Option<f64>> = contact
        .positions_mm
        .iter()
        .map(|p| p.map(|p| gel.to_gel(p)[2]))
        .collect();
    let (h, w) = ((rows - 1) * per_pitch + 1, (cols - 1) * per_pitch + 1);
    let mut z_mm = vec![f32::NAN; h * w];
    for (i, out) in z_mm.iter_mut().enumerate() {
        let (fr, fc) = (
            (i / w) as f64 / per_pitch as f64,
            (i % w) as f64 / per_pitch as f64,
        );
        let (r, c) = ((fr as usize).min(rows - 2), (fc as usize).min(cols - 2));
        let (ar, ac) = (fr - r as f64, fc - c as f64);
        let at = |rr: usize, cc: usize| z[rr * cols + cc];
        if let (Some(a), Some(b), Some(cz), Some(d)) =
            (at(r, c), at(r, c + 1), at(r + 1, c), at(r + 1, c + 1))
        {
            let top = a * (1.0 - ac) + b * ac;
            let bottom = cz * (1.0 - ac) + d * ac;
            *out = (top * (1.0 - ar) + bottom * ar) as f32;
        }
    }
    let pitch = gel.pitch_mm;
    HeightMap {
        rows: h,
        cols: w,
        pixel_mm: pitch / per_pitch as f64,
        origin_mm: [
            -((cols - 1) as f64) / 2.0 * pitch,
            -((rows - 1) as f64) / 2.0 * pitch,
        ],
        z_mm,
    }
}

/// Writes the marker cloud and the deformed mesh of a stereo frame, coordinates and displacements
/// in `frame` (the gel's or the left camera's).
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_ply(
    paths: (&Path, &Path),
    frame_number: u32,
    shape: GridShape,
    triangles: &[[u32; 3]],
    contact: &ContactFrame,
    reprojection: &[Option<f64>],
    gel: &crate::GelFrame,
    frame: CoordinateFrame,
) -> Result<()> {
    let point = |p: &nalgebra::Point3<f64>| match frame {
        CoordinateFrame::Gel => gel.to_gel(*p),
        CoordinateFrame::LeftCamera => [p.x, p.y, p.z],
    };
    let vector = |d: nalgebra::Vector3<f64>| match frame {
        CoordinateFrame::Gel => gel.vector_to_gel(d),
        CoordinateFrame::LeftCamera => [d.x, d.y, d.z],
    };
    let cloud: Vec<MarkerPoint> = shape
        .indices()
        .enumerate()
        .filter_map(|(k, index)| {
            Some(MarkerPoint {
                index,
                position_mm: point(contact.positions_mm[k].as_ref()?),
                reprojection_error_px: reprojection[k].unwrap_or(0.0),
            })
        })
        .collect();
    let comment =
        format!("frame {frame_number}; reprojection_error 0 for markers predicted from their neighbours");
    write_marker_cloud(paths.0, &cloud, frame, &comment)?;
    let mut vertex_of = vec![u32::MAX; shape.count()];
    let mut mesh = TriangleMesh::default();
    let names = [
        "depth_mm",
        "displacement_mm",
        "dx_mm",
        "dy_mm",
        "dz_mm",
        "pressure_kPa",
        "in_contact",
    ];
    let mut props: Vec<Vec<f32>> = vec![Vec::new(); names.len()];
    for (k, p) in contact.positions_mm.iter().enumerate() {
        let Some(p) = p else { continue };
        vertex_of[k] = mesh.vertices_mm.len() as u32;
        mesh.vertices_mm.push(point(p));
        let d = contact.displacement_mm[k].unwrap_or_default();
        let [dx, dy, dz] = vector(d);
        let vals = [
            contact.depth_mm[k].unwrap_or(0.0),
            d.norm(),
            dx,
            dy,
            dz,
            contact.traction_kpa.get(k).map_or(0.0, |t| t[2]),
            f64::from(u8::from(contact.in_contact[k])),
        ];
        for (v, list) in vals.iter().zip(props.iter_mut()) {
            list.push(*v as f32);
        }
    }
    for t in triangles {
        let f = t.map(|i| vertex_of[i as usize]);
        if f.iter().all(|v| *v != u32::MAX) {
            mesh.faces.push(f);
        }
    }
    mesh.properties = names
        .iter()
        .zip(props)
        .map(|(n, values)| VertexProperty {
            name: (*n).to_owned(),
            values,
        })
        .collect();
    let comment = format!("frame {frame_number}; deformed marker surface");
    write_mesh(paths.1, &mesh, frame, &comment)?;
    Ok(())
}

/// The markers of one view for an overlay: reference position, current position, status, contact.
pub(crate) fn overlay_markers(
    reference: &[Point2],
    track: &TrackFrame,
    in_contact: &dyn Fn(usize) -> bool,
) -> Vec<OverlayMarker> {
    track
        .markers
        .iter()
        .enumerate()
        .filter_map(|(k, m)| {
            Some(OverlayMarker {
                reference_px: *reference.get(k)?,
                current_px: m.position_px?,
                status: m.status,
                in_contact: in_contact(k),
            })
        })
        .collect()
}

/// The overlay caption's items: frame, slip state, contact area and depth ("unknown" where the
/// sensor cannot tell).
pub(crate) fn caption(s: &FrameSummary) -> Vec<String> {
    let known = |v: Option<f64>, decimals: usize, unit: &str| {
        v.map_or_else(|| "unknown".to_owned(), |v| format!("{v:.decimals$} {unit}"))
    };
    vec![
        format!("frame {}", s.frame),
        s.slip.as_str().replace('_', " "),
        format!("area {}", known(s.contact_area_mm2, 1, "mm²")),
        format!("depth {}", known(s.max_depth_mm, 2, "mm")),
    ]
}

/// The marker surface of a stereo frame, for the contact-surface figure.
pub(crate) fn surface(shape: GridShape, contact: &ContactFrame) -> figures::Surface {
    figures::Surface {
        rows: usize::from(shape.rows),
        cols: usize::from(shape.cols),
        positions_mm: contact
            .positions_mm
            .iter()
            .map(|p| p.map(|p| [p.x, p.y, p.z]))
            .collect(),
        depth_mm: contact.depth_mm.clone(),
    }
}
