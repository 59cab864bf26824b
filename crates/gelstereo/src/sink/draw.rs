//! Drawing and geometry exports of one frame: PLY marker clouds and meshes, overlays with
//! displacement arrows, colour maps of dense fields, plots of the run.

use std::path::Path;

use gelstereo_core::{FrameSummary, GridShape, MarkerStatus, Point2, SlipState};
use gelstereo_io::plot::{self, LinePlot};
use gelstereo_io::ply::{MarkerPoint, TriangleMesh, VertexProperty, write_marker_cloud, write_mesh};
use gelstereo_tracking::{ContactFrame, DenseField, TrackFrame};
use opencv::core::{Mat, MatTraitConst, Point, Scalar};
use opencv::imgproc;

use crate::Result;

/// Writes the marker cloud and the deformed mesh of a stereo frame.
pub(crate) fn write_ply(
    paths: (&Path, &Path),
    frame: u32,
    shape: GridShape,
    triangles: &[[u32; 3]],
    contact: &ContactFrame,
    reprojection: &[Option<f64>],
) -> Result<()> {
    let cloud: Vec<MarkerPoint> = shape
        .indices()
        .enumerate()
        .filter_map(|(k, index)| {
            let p = contact.positions_mm[k]?;
            Some(MarkerPoint {
                index,
                position_mm: [p.x, p.y, p.z],
                reprojection_error_px: reprojection[k].unwrap_or(0.0),
            })
        })
        .collect();
    let comment = format!("frame {frame}; reprojection_error 0 for markers predicted from their neighbours");
    write_marker_cloud(paths.0, &cloud, &comment)?;
    let mut vertex_of = vec![u32::MAX; shape.count()];
    let mut mesh = TriangleMesh::default();
    let names = [
        "depth_mm",
        "displacement_mm",
        "dX_mm",
        "dY_mm",
        "dZ_mm",
        "load_mm",
        "in_contact",
    ];
    let mut props: Vec<Vec<f32>> = vec![Vec::new(); names.len()];
    for (k, p) in contact.positions_mm.iter().enumerate() {
        let Some(p) = p else { continue };
        vertex_of[k] = mesh.vertices_mm.len() as u32;
        mesh.vertices_mm.push([p.x, p.y, p.z]);
        let d = contact.displacement_mm[k].unwrap_or_default();
        let vals = [
            contact.depth_mm[k].unwrap_or(0.0),
            d.norm(),
            d.x,
            d.y,
            d.z,
            contact.load_mm.get(k).copied().unwrap_or(0.0),
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
    write_mesh(paths.1, &mesh, &format!("frame {frame}; deformed marker surface"))?;
    Ok(())
}

/// Draws displacement arrows (reference -> current, scaled) and the contact markers onto `image`.
pub(crate) fn overlay(
    image: &Mat,
    reference: &[Point2],
    track: &TrackFrame,
    in_contact: &dyn Fn(usize) -> bool,
    scale: f64,
    caption: &str,
) -> Result<Mat> {
    let mut out = Mat::default();
    if image.channels() == 1 {
        imgproc::cvt_color(image, &mut out, imgproc::COLOR_GRAY2BGR, 0)?;
    } else {
        out = image.try_clone()?;
    }
    let pt = |p: Point2| Point::new(p.x.round() as i32, p.y.round() as i32);
    for (k, m) in track.markers.iter().enumerate() {
        let Some(p) = m.position_px else { continue };
        let r = reference[k];
        let tip = Point2::new(r.x + scale * (p.x - r.x), r.y + scale * (p.y - r.y));
        let color = match m.status {
            MarkerStatus::Tracked => Scalar::new(0.0, 200.0, 0.0, 0.0),
            MarkerStatus::Predicted => Scalar::new(0.0, 160.0, 255.0, 0.0),
            MarkerStatus::Lost => Scalar::new(0.0, 0.0, 255.0, 0.0),
        };
        if in_contact(k) {
            imgproc::circle(
                &mut out,
                pt(p),
                5,
                Scalar::new(0.0, 0.0, 255.0, 0.0),
                1,
                imgproc::LINE_AA,
                0,
            )?;
        }
        imgproc::arrowed_line(&mut out, pt(r), pt(tip), color, 1, imgproc::LINE_AA, 0, 0.25)?;
    }
    imgproc::put_text(
        &mut out,
        caption,
        Point::new(6, 16),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.45,
        Scalar::new(0.0, 0.0, 0.0, 0.0),
        3,
        imgproc::LINE_AA,
        false,
    )?;
    imgproc::put_text(
        &mut out,
        caption,
        Point::new(6, 16),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.45,
        Scalar::new(255.0, 255.0, 255.0, 0.0),
        1,
        imgproc::LINE_AA,
        false,
    )?;
    Ok(out)
}

/// A colour map (jet, 0 .. the field's maximum) of a dense field, with a caption.
pub(crate) fn heatmap(field: &DenseField, caption: &str) -> Result<Mat> {
    let (_, hi) = field.range();
    let scale = if hi > 0.0 { 255.0 / hi } else { 0.0 };
    let bytes: Vec<u8> = field
        .values
        .iter()
        .map(|v| (v.max(0.0) * scale).round().clamp(0.0, 255.0) as u8)
        .collect();
    let grey = Mat::new_rows_cols_with_data(field.height as i32, field.width as i32, &bytes)?.try_clone()?;
    let mut colour = Mat::default();
    imgproc::apply_color_map(&grey, &mut colour, imgproc::COLORMAP_JET)?;
    let mut out = Mat::default();
    let (w, h) = (colour.cols().max(1), colour.rows().max(1));
    let k = (480.0 / f64::from(h)).max(1.0);
    imgproc::resize(
        &colour,
        &mut out,
        opencv::core::Size::new((f64::from(w) * k) as i32, (f64::from(h) * k) as i32),
        0.0,
        0.0,
        imgproc::INTER_LINEAR,
    )?;
    imgproc::put_text(
        &mut out,
        caption,
        Point::new(6, 18),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.5,
        Scalar::all(255.0),
        1,
        imgproc::LINE_AA,
        false,
    )?;
    Ok(out)
}

pub(crate) fn caption(s: &FrameSummary) -> String {
    format!(
        "frame {} {} area {:.2} mm2 depth {:.3} mm",
        s.frame,
        s.slip.as_str(),
        s.contact_area_mm2,
        s.max_depth_mm
    )
}

/// Plots of a run's contact area, largest depth (stereo) and slip state over the frames, as
/// `(relative name, plot)`.
pub(crate) fn run_plots(history: &[FrameSummary], stereo: bool) -> Vec<(&'static str, LinePlot)> {
    let x = |f: &FrameSummary| f64::from(f.frame);
    let area: Vec<(f64, f64)> = history.iter().map(|f| (x(f), f.contact_area_mm2)).collect();
    let mut plots = vec![(
        "plots/contact_area.png",
        LinePlot::new("contact area", "frame", "mm^2").with_series("contact area", [200, 80, 0], area),
    )];
    if stereo {
        let depth: Vec<(f64, f64)> = history.iter().map(|f| (x(f), f.max_depth_mm)).collect();
        plots.push((
            "plots/max_depth.png",
            LinePlot::new("largest indentation depth", "frame", "mm").with_series(
                "max depth",
                [0, 120, 220],
                depth,
            ),
        ));
    }
    let slip: Vec<(f64, f64)> = history
        .iter()
        .map(|f| (x(f), f64::from(slip_level(f.slip))))
        .collect();
    let cats = [
        SlipState::NoContact,
        SlipState::Stick,
        SlipState::PartialSlip,
        SlipState::GrossSlip,
    ]
    .map(|s| s.as_str().to_owned())
    .to_vec();
    plots.push((
        "plots/slip.png",
        LinePlot {
            categories: cats,
            ..LinePlot::new("slip state", "frame", "")
        }
        .with_series("slip", [40, 40, 200], slip),
    ));
    plots
}

/// Writes `plot` as a PNG at `path`.
pub(crate) fn write_plot(path: &Path, plot: &LinePlot) -> Result<()> {
    Ok(plot::write(path, plot)?)
}

fn slip_level(s: SlipState) -> u8 {
    match s {
        SlipState::NoContact => 0,
        SlipState::Stick => 1,
        SlipState::PartialSlip => 2,
        SlipState::GrossSlip => 3,
    }
}
