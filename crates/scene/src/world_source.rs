//! What a scene's world is built from, as bytes: its shapes, materials, textures and
//! emitters as parsed (defaults and `-D` overrides substituted), without the sensor and the
//! integrator. Two loads whose world sources are equal, and whose named files hold the same
//! bytes, describe the same world: frames of a shot that differ only in their camera can
//! share one built world (the farm's workers do, so a batch's meshes are loaded and its BVH
//! built once).
//!
//! The source names files as written (`filename="models/a.ply"`); their bytes are not in it.
//! The caller pins them (the farm by the digests of its bundle's files). Where the text came
//! from (a file's lines, the directory it was read from) is not in it either: it does not
//! change what is built.

use std::collections::HashMap;
use std::path::Path;
use std::rc::Rc;

use crate::error::SceneError;
use crate::xml::{self, Category, Child, Node, ObjRef, Spectrum, Value};
use crate::Limits;

/// The world source of the scene at `path` with `overrides` (see the module docs). Only the
/// scene's text is read (the files it includes too): no mesh or image is opened.
pub fn world_source(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
) -> Result<Vec<u8>, SceneError> {
    let parsed = xml::parse_file(path, overrides, limits)?;
    let mut e = Encoder::default();
    e.strs(&parsed.search_paths);
    let objects: Vec<&Child> = (parsed.objects.iter())
        .filter(|c| !is_frame_only(&c.obj, &parsed.ids))
        .collect();
    e.len(objects.len());
    for c in objects {
        e.child(c);
    }
    // Every object another names by `ref`, wherever it is defined, so that a reference
    // pins its target's contents (ids are unique: the name alone is ambiguous across loads).
    let mut ids: Vec<(&String, &Rc<Node>)> = (parsed.ids.iter())
        .filter(|(_, n)| !frame_only(n.category))
        .collect();
    ids.sort_by(|a, b| a.0.cmp(b.0));
    e.len(ids.len());
    for (id, node) in ids {
        e.str(id);
        e.node(node);
    }
    Ok(e.out)
}

/// The categories that make a frame, not its world: the camera and how its image is made.
fn frame_only(c: Category) -> bool {
    matches!(
        c,
        Category::Sensor
            | Category::Integrator
            | Category::Film
            | Category::RFilter
            | Category::Sampler
    )
}

fn is_frame_only(obj: &ObjRef, ids: &HashMap<String, Rc<Node>>) -> bool {
    match obj {
        ObjRef::Inline(n) => frame_only(n.category),
        ObjRef::Ref { id, .. } => ids.get(id).is_some_and(|n| frame_only(n.category)),
    }
}

/// A length-prefixed, tagged encoding: two different trees never encode to the same bytes.
#[derive(Default)]
struct Encoder {
    out: Vec<u8>,
}

impl Encoder {
    fn len(&mut self, n: usize) {
        self.out.extend_from_slice(&(n as u64).to_le_bytes());
    }

    fn str(&mut self, s: &str) {
        self.len(s.len());
        self.out.extend_from_slice(s.as_bytes());
    }

    fn strs(&mut self, v: &[String]) {
        self.len(v.len());
        for s in v {
            self.str(s);
        }
    }

    fn opt_str(&mut self, s: Option<&str>) {
        match s {
            None => self.out.push(0),
            Some(s) => {
                self.out.push(1);
                self.str(s);
            }
        }
    }

    fn f64s(&mut self, v: &[f64]) {
        for x in v {
            self.out.extend_from_slice(&x.to_bits().to_le_bytes());
        }
    }

    fn f32s(&mut self, v: &[f32]) {
        for x in v {
            self.out.extend_from_slice(&x.to_bits().to_le_bytes());
        }
    }

    fn node(&mut self, n: &Node) {
        self.str(n.category.tag());
        self.str(&n.plugin);
        self.opt_str(n.id.as_deref());
        self.len(n.props.len());
        for p in &n.props {
            self.str(&p.name);
            self.value(&p.value);
        }
        self.len(n.children.len());
        for c in &n.children {
            self.child(c);
        }
    }

    fn child(&mut self, c: &Child) {
        self.opt_str(c.name.as_deref());
        match &c.obj {
            ObjRef::Inline(n) => {
                self.out.push(0);
                self.node(n);
            }
            ObjRef::Ref { id, .. } => {
                self.out.push(1);
                self.str(id);
            }
        }
    }

    fn value(&mut self, v: &Value) {
        match v {
            Value::Integer(i) => {
                self.out.push(0);
                self.out.extend_from_slice(&i.to_le_bytes());
            }
            Value::Float(x) => {
                self.out.push(1);
                self.f64s(&[*x]);
            }
            Value::Boolean(b) => self.out.extend_from_slice(&[2, u8::from(*b)]),
            Value::String(s) => {
                self.out.push(3);
                self.str(s);
            }
            Value::Rgb(c) => {
                self.out.push(4);
                self.f32s(&c.to_array());
            }
            Value::Spectrum(Spectrum::Uniform(x)) => {
                self.out.push(5);
                self.f32s(&[*x]);
            }
            Value::Spectrum(Spectrum::Pairs(pairs)) => {
                self.out.push(6);
                self.len(pairs.len());
                for (w, x) in pairs {
                    self.f32s(&[*w, *x]);
                }
            }
            Value::Point(p) => {
                self.out.push(7);
                self.f64s(&p.to_array());
            }
            Value::Vector(d) => {
                self.out.push(8);
                self.f64s(&d.to_array());
            }
            Value::Transform(m) => {
                self.out.push(9);
                self.f64s(&m.to_cols_array());
            }
            Value::CommandLine(s) => {
                self.out.push(10);
                self.str(s);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn source_of(xml_body: &str, overrides: &[(&str, &str)]) -> Vec<u8> {
        // A directory a call (tests run in parallel), removed with what it holds.
        static CALLS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir =
            std::env::temp_dir().join(format!("pathfarm-world-source-{}-{n}", std::process::id()));
        std::fs::create_dir_all(dir.join("meshes")).unwrap();
        let path = dir.join("scene.xml");
        let xml = format!("<scene version=\"3.0.0\">{DEFAULTS}{xml_body}</scene>");
        std::fs::write(&path, xml).unwrap();
        let ov: Vec<(String, String)> = (overrides.iter())
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect();
        let got = world_source(&path, &ov, &Limits::default()).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        got
    }

    const CAMERA_A: &str = r#"<sensor type="perspective"><float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$resx"/></film></sensor>"#;
    const CAMERA_B: &str = r#"<sensor type="perspective"><float name="fov" value="35"/>

        <transform name="to_world"><lookat origin="0.5, 1, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$resx"/></film></sensor>"#;
    const DEFAULTS: &str = r#"<default name="resx" value="64"/><default name="r" value="0.5"/>"#;
    const WORLD: &str = r#"<bsdf type="diffuse" id="grey"><rgb name="reflectance" value="$r"/></bsdf>
        <shape type="sphere"><float name="radius" value="2"/><ref id="grey"/></shape>
        <emitter type="constant"/>"#;

    #[test]
    fn frames_differing_in_their_camera_or_integrator_share_a_world_source() {
        let a = source_of(&format!("{CAMERA_A}{WORLD}"), &[]);
        let b = source_of(
            &format!("<integrator type=\"path\"/>{WORLD}{CAMERA_B}"),
            &[("resx", "32")],
        );
        assert_eq!(a, b);
    }

    #[test]
    fn anything_the_world_is_built_from_changes_its_source() {
        let base = source_of(&format!("{CAMERA_A}{WORLD}"), &[]);
        let changed = [
            source_of(&format!("{CAMERA_A}{WORLD}"), &[("r", "0.6")]),
            source_of(
                &format!("{CAMERA_A}{}", WORLD.replace("\"2\"", "\"2.5\"")),
                &[],
            ),
            source_of(
                &format!(
                    "{CAMERA_A}{}",
                    WORLD.replace("constant", "constant\" id=\"sky")
                ),
                &[],
            ),
            source_of(
                &format!("{CAMERA_A}{WORLD}<shape type=\"rectangle\"/>"),
                &[],
            ),
            source_of(&format!("{CAMERA_A}<path value=\"meshes\"/>{WORLD}"), &[]),
        ];
        for (i, c) in changed.iter().enumerate() {
            assert_ne!(&base, c, "change {i} left the world source as it was");
        }
    }
}
