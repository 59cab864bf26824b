//! PLY export (binary little-endian, written with `ply-rs-bw`): per-frame marker point clouds and
//! triangle meshes with extra per-vertex properties. Both read in Open3D
//! (`o3d.io.read_point_cloud` / `read_triangle_mesh`) and MeshLab, which use `x y z` and the
//! `vertex_indices` face list and ignore (or show as scalar fields) the extra properties.
//!
//! Coordinates are mm, stored as `float`, in the [`CoordinateFrame`] the caller chooses (the LEFT
//! camera's, x right, y down, z forward, or the gel's), named in a header comment.
//!
//! Marker cloud layout:
//! ```text
//! element vertex N
//! property float x
//! property float y
//! property float z
//! property int row
//! property int col
//! property float reprojection_error
//! ```
//! Mesh layout: `x y z`, then one `float` property per [`VertexProperty`], then
//! `element face M` / `property list uchar int vertex_indices`.
//!
//! Checked with Open3D 0.20: `read_point_cloud` gives the positions; `o3d.t.io.read_point_cloud`
//! also the `row`, `col` (Int32) and `reprojection_error` attributes (it skips 16-bit integers,
//! hence `int`); `read_triangle_mesh` gives a mesh's vertices and faces, and its extra vertex
//! properties come with `o3d.t.io.read_point_cloud` on the same file.

use std::io::Write as _;
use std::path::Path;

use gelstereo_core::GridIndex;
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{
    Addable, DefaultElement, ElementDef, Encoding, Ply, Property, PropertyDef, PropertyType, ScalarType,
};
use ply_rs_bw::writer::Writer;

use crate::{Error, Result};

/// The frame a PLY's coordinates are in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CoordinateFrame {
    /// The gel frame: origin at the centre of the reference surface, x along the lattice's
    /// columns, y along its rows, z the surface's normal away from the cameras (the transform
    /// from the left camera is in the output's `gel.json`).
    #[default]
    Gel,
    /// The left camera frame: x right, y down, z forward.
    LeftCamera,
}

impl CoordinateFrame {
    /// The header comment that names the frame.
    fn header_comment(self) -> &'static str {
        match self {
            Self::Gel => {
                "gelstereo: mm, gel frame (origin at the centre of the reference surface, x along the \
                 columns, y along the rows, z the surface normal away from the cameras; gel.json)"
            }
            Self::LeftCamera => "gelstereo: mm, left camera frame (x right, y down, z forward)",
        }
    }
}

impl std::str::FromStr for CoordinateFrame {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "gel" => Ok(Self::Gel),
            "camera" => Ok(Self::LeftCamera),
            _ => Err(format!("'{s}': expected gel or camera")),
        }
    }
}

/// One reconstructed marker of a point cloud.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerPoint {
    /// The marker's grid identity.
    pub index: GridIndex,
    /// Position in the cloud's [`CoordinateFrame`], mm.
    pub position_mm: [f64; 3],
    /// Reprojection error of the triangulated point (the larger of the two views), px.
    pub reprojection_error_px: f64,
}

/// A named per-vertex scalar of a mesh (e.g. `displacement_mm`, `depth_mm`).
#[derive(Debug, Clone, PartialEq)]
pub struct VertexProperty {
    /// Property name as it appears in the PLY header (ASCII letters, digits and `_`).
    pub name: String,
    /// One value per vertex.
    pub values: Vec<f32>,
}

/// A triangle mesh with extra per-vertex properties.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TriangleMesh {
    /// Vertex positions in the mesh's [`CoordinateFrame`], mm.
    pub vertices_mm: Vec<[f64; 3]>,
    /// Extra per-vertex scalars, each with one value per vertex.
    pub properties: Vec<VertexProperty>,
    /// Triangles as vertex numbers, in the winding order the caller chooses (consistently).
    pub faces: Vec<[u32; 3]>,
}

fn invalid(path: &Path, what: String) -> Error {
    Error::Io {
        path: path.to_path_buf(),
        source: std::io::Error::new(std::io::ErrorKind::InvalidData, what),
    }
}

fn scalar(name: &str, t: ScalarType) -> PropertyDef {
    PropertyDef::new(name.to_owned(), PropertyType::Scalar(t))
}

fn finite3(p: &[f64; 3]) -> bool {
    p.iter().all(|v| v.is_finite())
}

fn write_file(path: &Path, ply: &mut Ply<DefaultElement>) -> Result<()> {
    let io = |source: std::io::Error| Error::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut buf = Vec::new();
    Writer::new().write_ply(&mut buf, ply).map_err(io)?;
    // Through a temporary file: a run killed mid-write leaves no cut PLY behind.
    let mut f = crate::AtomicFile::create(path)?;
    f.write_all(&buf).map_err(io)?;
    f.commit()
}

fn new_ply(frame: CoordinateFrame, comment: &str) -> Ply<DefaultElement> {
    let mut ply = Ply::<DefaultElement>::new();
    ply.header.encoding = Encoding::BinaryLittleEndian;
    ply.header.comments.push(frame.header_comment().to_owned());
    for line in comment.lines().filter(|l| !l.trim().is_empty()) {
        ply.header.comments.push(line.trim().to_owned());
    }
    ply
}

/// Writes `points` as a binary little-endian PLY point cloud to `path` (layout in the module docs);
/// `frame` and the `comment` lines go into the header. Points with a non-finite coordinate are
/// rejected.
pub fn write_marker_cloud(
    path: &Path,
    points: &[MarkerPoint],
    frame: CoordinateFrame,
    comment: &str,
) -> Result<()> {
    if let Some(p) = points
        .iter()
        .find(|p| !finite3(&p.position_mm) || !p.reprojection_error_px.is_finite())
    {
        return Err(invalid(
            path,
            format!("marker {} has a non-finite position or error: {:?}", p.index, p),
        ));
    }
    let mut ply = new_ply(frame, comment);
    let mut vertex = ElementDef::new("vertex".to_owned());
    for name in ["x", "y", "z"] {
        vertex.properties.add(scalar(name, ScalarType::Float));
    }
    // `int`, not `ushort`: Open3D's tensor reader skips 16-bit properties.
    vertex.properties.add(scalar("row", ScalarType::Int));
    vertex.properties.add(scalar("col", ScalarType::Int));
    vertex
        .properties
        .add(scalar("reprojection_error", ScalarType::Float));
    ply.header.elements.add(vertex);
    let list = points
        .iter()
        .map(|p| {
            let mut e = DefaultElement::new();
            for (name, v) in ["x", "y", "z"].iter().zip(p.position_mm) {
                e.insert((*name).to_owned(), Property::Float(v as f32));
            }
            e.insert("row".to_owned(), Property::Int(i32::from(p.index.row)));
            e.insert("col".to_owned(), Property::Int(i32::from(p.index.col)));
            e.insert(
                "reprojection_error".to_owned(),
                Property::Float(p.reprojection_error_px as f32),
            );
            e
        })
        .collect();
    ply.payload.insert("vertex".to_owned(), list);
    write_file(path, &mut ply)
}

/// Writes `mesh` as a binary little-endian PLY triangle mesh to `path` (layout in the module docs).
/// Checks that every property has one value per vertex, that property names are plain identifiers
/// distinct from `x y z`, and that faces refer to existing vertices.
pub fn write_mesh(path: &Path, mesh: &TriangleMesh, frame: CoordinateFrame, comment: &str) -> Result<()> {
    let n = mesh.vertices_mm.len();
    if let Some(i) = mesh.vertices_mm.iter().position(|p| !finite3(p)) {
        return Err(invalid(
            path,
            format!("vertex {i} has a non-finite position {:?}", mesh.vertices_mm[i]),
        ));
    }
    let mut names: Vec<&str> = vec!["x", "y", "z"];
    for p in &mesh.properties {
        let ok = !p.name.is_empty()
            && p.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            && !names.contains(&p.name.as_str());
        if !ok {
            return Err(invalid(
                path,
                format!(
                    "vertex property name '{}': expected a new identifier of [A-Za-z0-9_]",
                    p.name
                ),
            ));
        }
        if p.values.len() != n {
            return Err(invalid(
                path,
                format!(
                    "vertex property '{}': {} values, expected one per vertex ({n})",
                    p.name,
                    p.values.len()
                ),
            ));
        }
        names.push(&p.name);
    }
    if let Some(f) = mesh.faces.iter().find(|f| f.iter().any(|&v| v as usize >= n)) {
        return Err(invalid(
            path,
            format!("face {f:?} refers to a vertex beyond the {n} vertices"),
        ));
    }
    if n > i32::MAX as usize {
        return Err(invalid(
            path,
            format!("{n} vertices: PLY int indices hold at most {}", i32::MAX),
        ));
    }
    let mut ply = new_ply(frame, comment);
    let mut vertex = ElementDef::new("vertex".to_owned());
    for name in &names {
        vertex.properties.add(scalar(name, ScalarType::Float));
    }
    ply.header.elements.add(vertex);
    let mut face = ElementDef::new("face".to_owned());
    face.properties.add(PropertyDef::new(
        "vertex_indices".to_owned(),
        PropertyType::List(ScalarType::UChar, ScalarType::Int),
    ));
    ply.header.elements.add(face);
    let vertices = (0..n)
        .map(|i| {
            let mut e = DefaultElement::new();
            for (name, v) in ["x", "y", "z"].iter().zip(mesh.vertices_mm[i]) {
                e.insert((*name).to_owned(), Property::Float(v as f32));
            }
            for p in &mesh.properties {
                e.insert(p.name.clone(), Property::Float(p.values[i]));
            }
            e
        })
        .collect();
    let faces = mesh
        .faces
        .iter()
        .map(|f| {
            let mut e = DefaultElement::new();
            // Checked above: every index is below n <= i32::MAX.
            e.insert(
                "vertex_indices".to_owned(),
                Property::ListInt(f.iter().map(|&v| v as i32).collect()),
            );
            e
        })
        .collect();
    ply.payload.insert("vertex".to_owned(), vertices);
    ply.payload.insert("face".to_owned(), faces);
    write_file(path, &mut ply)
}

/// Reads a marker cloud written by [`write_marker_cloud`] (or any PLY whose vertices carry
/// `x y z row col reprojection_error`).
pub fn read_marker_cloud(path: &Path) -> Result<Vec<MarkerPoint>> {
    let io = |source: std::io::Error| Error::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut f = std::io::BufReader::new(std::fs::File::open(path).map_err(io)?);
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut f)
        .map_err(|e| invalid(path, format!("not a readable PLY file: {e}")))?;
    let Some(vertices) = ply.payload.get("vertex") else {
        return Err(invalid(path, "no 'vertex' element".to_owned()));
    };
    let num = |e: &DefaultElement, k: &str| -> Result<f64> {
        match e.get(k) {
            Some(Property::Float(v)) => Ok(f64::from(*v)),
            Some(Property::Double(v)) => Ok(*v),
            Some(Property::UShort(v)) => Ok(f64::from(*v)),
            Some(Property::Int(v)) => Ok(f64::from(*v)),
            Some(Property::UInt(v)) => Ok(f64::from(*v)),
            _ => Err(invalid(path, format!("vertex property '{k}': expected a number"))),
        }
    };
    let index = |e: &DefaultElement, k: &str| -> Result<u16> {
        let v = num(e, k)?;
        if v >= 0.0 && v <= f64::from(u16::MAX) && v.fract() == 0.0 {
            Ok(v as u16)
        } else {
            Err(invalid(
                path,
                format!("vertex property '{k}': expected an integer 0-65535, found {v}"),
            ))
        }
    };
    vertices
        .iter()
        .map(|e| {
            Ok(MarkerPoint {
                index: GridIndex::new(index(e, "row")?, index(e, "col")?),
                position_mm: [num(e, "x")?, num(e, "y")?, num(e, "z")?],
                reprojection_error_px: num(e, "reprojection_error")?,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error and its sources, as `anyhow`'s `{:#}` shows them.
    fn chain(e: &Error) -> String {
        let mut s = e.to_string();
        let mut src = std::error::Error::source(e);
        while let Some(c) = src {
            s = format!("{s}: {c}");
            src = c.source();
        }
        s
    }

    #[test]
    fn marker_cloud_round_trips_through_a_binary_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("000000.ply");
        let points: Vec<MarkerPoint> = (0..5u16)
            .map(|i| MarkerPoint {
                index: GridIndex::new(i, 22 - i),
                position_mm: [
                    f64::from(i) * 0.6 - 1.2,
                    -0.3 * f64::from(i),
                    25.0 + 0.01 * f64::from(i),
                ],
                reprojection_error_px: 0.05 * f64::from(i),
            })
            .collect();
        write_marker_cloud(&path, &points, CoordinateFrame::LeftCamera, "frame 0").unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let header = String::from_utf8_lossy(&bytes[..bytes.len().min(400)]).to_string();
        assert!(
            header.starts_with("ply\nformat binary_little_endian 1.0\n"),
            "{header}"
        );
        for line in [
            "element vertex 5",
            "property int row",
            "property float reprojection_error",
            "comment frame 0",
        ] {
            assert!(header.contains(line), "missing '{line}' in {header}");
        }
        let back = read_marker_cloud(&path).unwrap();
        assert_eq!(back.len(), points.len());
        for (a, b) in back.iter().zip(&points) {
            assert_eq!(a.index, b.index);
            // f32 storage: 1e-5 mm at 25 mm is well within f32's 24-bit mantissa (~2e-6 relative).
            for k in 0..3 {
                assert!((a.position_mm[k] - b.position_mm[k]).abs() < 1e-5);
            }
            assert!((a.reprojection_error_px - b.reprojection_error_px).abs() < 1e-6);
        }
        let nan = [MarkerPoint {
            position_mm: [f64::NAN, 0.0, 1.0],
            ..points[0]
        }];
        let err = chain(&write_marker_cloud(&path, &nan, CoordinateFrame::LeftCamera, "").unwrap_err());
        assert!(err.contains("000000.ply") && err.contains("non-finite"), "{err}");
    }

    #[test]
    fn mesh_has_properties_and_faces_and_rejects_bad_input() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mesh.ply");
        let mesh = TriangleMesh {
            vertices_mm: vec![
                [0.0, 0.0, 25.0],
                [0.6, 0.0, 25.0],
                [0.0, 0.6, 25.0],
                [0.6, 0.6, 24.8],
            ],
            properties: vec![VertexProperty {
                name: "depth_mm".into(),
                values: vec![0.0, 0.0, 0.0, 0.2],
            }],
            faces: vec![[0, 1, 2], [1, 3, 2]],
        };
        write_mesh(&path, &mesh, CoordinateFrame::Gel, "contact surface").unwrap();
        let mut f = std::io::BufReader::new(std::fs::File::open(&path).unwrap());
        let ply = Parser::<DefaultElement>::new().read_ply(&mut f).unwrap();
        assert_eq!(ply.header.encoding, Encoding::BinaryLittleEndian);
        let v = &ply.payload["vertex"];
        assert_eq!(v.len(), 4);
        assert_eq!(v[3]["depth_mm"], Property::Float(0.2));
        assert_eq!(v[3]["z"], Property::Float(24.8));
        assert_eq!(
            ply.payload["face"][1]["vertex_indices"],
            Property::ListInt(vec![1, 3, 2])
        );

        let bad_face = TriangleMesh {
            faces: vec![[0, 1, 4]],
            ..mesh.clone()
        };
        assert!(
            chain(&write_mesh(&path, &bad_face, CoordinateFrame::Gel, "").unwrap_err())
                .contains("beyond the 4 vertices")
        );
        let short = TriangleMesh {
            properties: vec![VertexProperty {
                name: "depth_mm".into(),
                values: vec![0.0],
            }],
            ..mesh.clone()
        };
        assert!(
            chain(&write_mesh(&path, &short, CoordinateFrame::Gel, "").unwrap_err())
                .contains("1 values, expected one per vertex (4)")
        );
        let clash = TriangleMesh {
            properties: vec![VertexProperty {
                name: "x".into(),
                values: vec![0.0; 4],
            }],
            ..mesh
        };
        assert!(chain(&write_mesh(&path, &clash, CoordinateFrame::Gel, "").unwrap_err()).contains("'x'"));
    }
}
