//! Typed access to a plugin's properties, with consumed-tracking so that
//! unknown (misspelt) parameters are reported instead of silently ignored.

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

use glam::{DMat4, Vec3};

use crate::desc::Location;
use crate::error::SceneError;
use crate::spectrum;
use crate::xml::{invalid, Category, Child, Node, ObjRef, Prop, Spectrum, Value};

/// A nested object with `ref`s already followed.
#[derive(Clone, Debug)]
pub(crate) struct Resolved {
    /// The `name` attribute of the nested element or `<ref>`.
    pub name: Option<String>,
    pub node: Rc<Node>,
    /// Where the object was written or referenced (the `<ref>` line for refs).
    pub loc: Location,
}

/// Follow a [`Child`] to its node, erroring on undefined ids.
pub(crate) fn resolve(
    child: &Child,
    ids: &HashMap<String, Rc<Node>>,
) -> Result<Resolved, SceneError> {
    match &child.obj {
        ObjRef::Inline(n) => Ok(Resolved {
            name: child.name.clone(),
            node: n.clone(),
            loc: n.loc.clone(),
        }),
        ObjRef::Ref { id, loc } => match ids.get(id) {
            Some(n) => Ok(Resolved {
                name: child.name.clone(),
                node: n.clone(),
                loc: loc.clone(),
            }),
            None => Err(invalid(loc, format!("reference to undefined id '{id}'"))),
        },
    }
}

impl Resolved {
    /// Check that the object is of `category`, else an error at its element saying what was
    /// `expected` ("a bsdf") and what it is.
    pub(crate) fn expect(&self, category: Category, expected: &str) -> Result<(), SceneError> {
        if self.node.category == category {
            return Ok(());
        }
        Err(invalid(
            &self.loc,
            format!(
                "expected {expected}, got a {} {}",
                self.node.plugin,
                self.node.category.tag()
            ),
        ))
    }
}

/// A plugin's properties and nested objects, tracking which were consumed.
pub(crate) struct Props {
    node: Rc<Node>,
    children: Vec<Resolved>,
    used_props: RefCell<Vec<bool>>,
    used_children: RefCell<Vec<bool>>,
}

impl Props {
    /// Wrap `node`, resolving its nested `ref`s against `ids`.
    pub(crate) fn new(node: Rc<Node>, ids: &HashMap<String, Rc<Node>>) -> Result<Self, SceneError> {
        let children = node
            .children
            .iter()
            .map(|c| resolve(c, ids))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            used_props: RefCell::new(vec![false; node.props.len()]),
            used_children: RefCell::new(vec![false; children.len()]),
            node,
            children,
        })
    }

    pub(crate) fn loc(&self) -> &Location {
        &self.node.loc
    }

    pub(crate) fn plugin(&self) -> &str {
        &self.node.plugin
    }

    /// The error for a plugin type this loader does not implement, at its element: "unsupported
    /// {kind} type '{plugin}' (supported: {supported})". (`kind` is given, not taken from the
    /// element's category: a `<sampler>` where the film belongs is an unsupported film.)
    pub(crate) fn unsupported(&self, kind: &str, supported: &str) -> SceneError {
        invalid(
            self.loc(),
            format!(
                "unsupported {kind} type '{}' (supported: {supported})",
                self.plugin()
            ),
        )
    }

    /// "roughconductor bsdf" etc., for messages.
    pub(crate) fn what(&self) -> String {
        format!("{} {}", self.node.plugin, self.node.category.tag())
    }

    /// Is a property or named nested object called `name` present? (Does not consume.)
    pub(crate) fn has(&self, name: &str) -> bool {
        self.node.props.iter().any(|p| p.name == name)
            || self
                .children
                .iter()
                .any(|c| c.name.as_deref() == Some(name))
    }

    /// Consume and return the raw property `name`.
    pub(crate) fn get(&self, name: &str) -> Option<&Prop> {
        let i = self.node.props.iter().position(|p| p.name == name)?;
        self.used_props.borrow_mut()[i] = true;
        Some(&self.node.props[i])
    }

    pub(crate) fn type_error(&self, p: &Prop, expected: &str) -> SceneError {
        invalid(
            &p.loc,
            format!(
                "parameter '{}' of {} has type <{}>, expected {expected}",
                p.name,
                self.what(),
                p.value.type_name()
            ),
        )
    }

    /// A `-D name=value` parameter whose text is not of the parameter's type.
    fn command_line_error(&self, p: &Prop, text: &str, expected: &str) -> SceneError {
        invalid(
            &p.loc,
            format!(
                "-D {}={text}: parameter '{}' of {} must be {expected}",
                p.name,
                p.name,
                self.what()
            ),
        )
    }

    pub(crate) fn float_opt(&self, name: &str) -> Result<Option<f32>, SceneError> {
        let Some((v, loc)) = self.f64_opt(name)? else {
            return Ok(None);
        };
        let f = v as f32;
        if !f.is_finite() {
            return Err(invalid(
                &loc,
                format!("parameter '{name}' is {v:e}, beyond the range of a 32-bit float"),
            ));
        }
        Ok(Some(f))
    }

    /// A finite number in double precision, with its location.
    pub(crate) fn f64_opt(&self, name: &str) -> Result<Option<(f64, Location)>, SceneError> {
        let Some(p) = self.get(name) else {
            return Ok(None);
        };
        let v = match &p.value {
            Value::Float(f) => *f,
            Value::Integer(i) => *i as f64,
            Value::CommandLine(s) => s
                .trim()
                .parse::<f64>()
                .map_err(|_| self.command_line_error(p, s, "a number"))?,
            _ => return Err(self.type_error(p, "<float>")),
        };
        if !v.is_finite() {
            return Err(invalid(
                &p.loc,
                format!("parameter '{name}' must be a finite number (got {v})"),
            ));
        }
        Ok(Some((v, p.loc.clone())))
    }

    pub(crate) fn float(&self, name: &str, default: f32) -> Result<f32, SceneError> {
        Ok(self.float_opt(name)?.unwrap_or(default))
    }

    pub(crate) fn int_opt(&self, name: &str) -> Result<Option<(i64, Location)>, SceneError> {
        let Some(p) = self.get(name) else {
            return Ok(None);
        };
        match &p.value {
            Value::Integer(i) => Ok(Some((*i, p.loc.clone()))),
            Value::CommandLine(s) => match s.trim().parse::<i64>() {
                Ok(i) => Ok(Some((i, p.loc.clone()))),
                Err(_) => Err(self.command_line_error(p, s, "an integer")),
            },
            _ => Err(self.type_error(p, "<integer>")),
        }
    }

    /// An integer in `[min, max]`.
    pub(crate) fn int_in(
        &self,
        name: &str,
        default: i64,
        min: i64,
        max: i64,
    ) -> Result<i64, SceneError> {
        let v = self.in_range(name, self.int_opt(name)?, min, max, |v| v.to_string())?;
        Ok(v.unwrap_or(default))
    }

    /// The `value` of the parameter `name`, as read by [`Props::int_opt`] or
    /// [`Props::f64_opt`], checked to be in `[min, max]`: outside, an error at its line
    /// "parameter '{name}' of {plugin} must be in [min, max] (got v)", `show` writing the
    /// numbers.
    pub(crate) fn in_range<T: PartialOrd + Copy>(
        &self,
        name: &str,
        value: Option<(T, Location)>,
        min: T,
        max: T,
        show: impl Fn(T) -> String,
    ) -> Result<Option<T>, SceneError> {
        match value {
            Some((v, loc)) if v < min || v > max => Err(invalid(
                &loc,
                format!(
                    "parameter '{name}' of {} must be in [{}, {}] (got {})",
                    self.what(),
                    show(min),
                    show(max),
                    show(v)
                ),
            )),
            v => Ok(v.map(|(v, _)| v)),
        }
    }

    /// An integer in `[min, max]` where `max` is the resource limit `limit` (named in the error).
    pub(crate) fn int_limited(
        &self,
        name: &str,
        default: i64,
        min: i64,
        max: i64,
        limit: &str,
    ) -> Result<i64, SceneError> {
        match self.int_opt(name)? {
            None => Ok(default),
            Some((v, loc)) if v > max => Err(invalid(
                &loc,
                format!(
                    "parameter '{name}' of {} is {v}, more than the limit of {max} ({limit})",
                    self.what()
                ),
            )),
            Some((v, loc)) if v < min => Err(invalid(
                &loc,
                format!(
                    "parameter '{name}' of {} must be at least {min} (got {v})",
                    self.what()
                ),
            )),
            Some((v, _)) => Ok(v),
        }
    }

    pub(crate) fn bool(&self, name: &str, default: bool) -> Result<bool, SceneError> {
        let Some(p) = self.get(name) else {
            return Ok(default);
        };
        match &p.value {
            Value::Boolean(b) => Ok(*b),
            Value::CommandLine(s) => match s.trim() {
                "true" => Ok(true),
                "false" => Ok(false),
                _ => Err(self.command_line_error(p, s, "true or false")),
            },
            _ => Err(self.type_error(p, "<boolean>")),
        }
    }

    /// A keyword parameter `name`: `default` when absent, else the value [`Keyword::NAMES`]
    /// pairs with the word; any other word is an error at its line naming the parameter, its
    /// plugin and the words it takes.
    pub(crate) fn keyword<T: Keyword>(&self, name: &str, default: T) -> Result<T, SceneError> {
        let Some((word, loc)) = self.string_opt(name)? else {
            return Ok(default);
        };
        let key = match T::CASE {
            Case::Insensitive => word.to_ascii_lowercase(),
            Case::Sensitive => word.clone(),
        };
        if let Some((_, v)) = T::NAMES.iter().find(|(n, _)| *n == key) {
            return Ok(*v);
        }
        let names: Vec<&str> = T::NAMES.iter().map(|(n, _)| *n).collect();
        Err(invalid(
            &loc,
            format!(
                "parameter '{name}' of {} must be one of {} (got \"{word}\")",
                self.what(),
                names.join(", ")
            ),
        ))
    }

    pub(crate) fn string_opt(&self, name: &str) -> Result<Option<(String, Location)>, SceneError> {
        let Some(p) = self.get(name) else {
            return Ok(None);
        };
        match &p.value {
            Value::String(s) | Value::CommandLine(s) => Ok(Some((s.clone(), p.loc.clone()))),
            _ => Err(self.type_error(p, "<string>")),
        }
    }

    /// A `<point>` (or `<vector>`) property.
    pub(crate) fn point_opt(&self, name: &str) -> Result<Option<Vec3>, SceneError> {
        let Some(p) = self.get(name) else {
            return Ok(None);
        };
        match p.value {
            Value::Point(v) | Value::Vector(v) => Ok(Some(v.as_vec3())),
            _ => Err(self.type_error(p, "<point> or <vector>")),
        }
    }

    pub(crate) fn transform_opt(&self, name: &str) -> Result<Option<DMat4>, SceneError> {
        let Some(p) = self.get(name) else {
            return Ok(None);
        };
        match p.value {
            Value::Transform(m) => Ok(Some(m)),
            _ => Err(self.type_error(p, "<transform>")),
        }
    }

    pub(crate) fn transform(&self, name: &str) -> Result<DMat4, SceneError> {
        Ok(self.transform_opt(name)?.unwrap_or(DMat4::IDENTITY))
    }

    /// A constant colour given as `<rgb>`, `<spectrum>` or a number.
    /// Nested textures are not looked at (see [`Props::named_child`]).
    pub(crate) fn color_opt(&self, name: &str) -> Result<Option<Vec3>, SceneError> {
        let usage = match self.node.category {
            Category::Emitter => spectrum::Use::Emission,
            _ => spectrum::Use::Reflectance,
        };
        let Some(c) = self.rgb_as(name, usage)? else {
            return Ok(None);
        };
        // Radiance, reflectance and the like: a negative value makes negative pixels.
        if c.min_element() < 0.0 {
            let p = self.get(name).expect("read above");
            return Err(invalid(
                &p.loc,
                format!(
                    "parameter '{name}' of {} is negative ({}, {}, {}): colours must be >= 0",
                    self.what(),
                    c.x,
                    c.y,
                    c.z
                ),
            ));
        }
        Ok(Some(c))
    }

    /// Three finite numbers given as a colour is: `<rgb>`, `<spectrum>` (uniform) or a
    /// number, of any sign. For what is not a colour, such as a conductor's complex index
    /// of refraction (fitted data may carry a small negative `eta`; only its square
    /// matters).
    pub(crate) fn rgb_opt(&self, name: &str) -> Result<Option<Vec3>, SceneError> {
        self.rgb_as(name, spectrum::Use::Unbounded)
    }

    /// Three numbers from `<rgb>`, `<spectrum>` (converted for `usage` as Mitsuba 3's RGB
    /// variants convert it) or a number.
    fn rgb_as(&self, name: &str, usage: spectrum::Use) -> Result<Option<Vec3>, SceneError> {
        let Some(p) = self.get(name) else {
            return Ok(None);
        };
        let c = match p.value {
            Value::Rgb(c) => c,
            Value::Spectrum(Spectrum::Uniform(s)) => match usage {
                spectrum::Use::Emission => spectrum::uniform_emission(s),
                _ => Vec3::splat(s),
            },
            Value::Spectrum(Spectrum::Pairs(ref pairs)) => spectrum::to_srgb(pairs, usage),
            Value::Float(f) => Vec3::splat(f as f32),
            Value::Integer(i) => Vec3::splat(i as f32),
            _ => return Err(self.type_error(p, "<rgb>, <spectrum> or <float>")),
        };
        if !c.is_finite() {
            return Err(invalid(
                &p.loc,
                format!("parameter '{name}' must be finite"),
            ));
        }
        Ok(Some(c))
    }

    /// Consume the nested object named `name` (e.g. `<texture name="reflectance">`).
    pub(crate) fn named_child(&self, name: &str) -> Option<Resolved> {
        let i = self
            .children
            .iter()
            .position(|c| c.name.as_deref() == Some(name))?;
        self.used_children.borrow_mut()[i] = true;
        Some(self.children[i].clone())
    }

    /// Consume all not-yet-consumed nested objects of `category` (named or not).
    pub(crate) fn children_of(&self, category: Category) -> Vec<Resolved> {
        let mut used = self.used_children.borrow_mut();
        let mut out = Vec::new();
        for (i, c) in self.children.iter().enumerate() {
            if !used[i] && c.node.category == category {
                used[i] = true;
                out.push(c.clone());
            }
        }
        out
    }

    /// The nested object of `category`, if there is one, consumed as by
    /// [`Props::children_of`]; a second is an error at its element, "{owner} has more than one
    /// {category}".
    pub(crate) fn at_most_one(
        &self,
        category: Category,
        owner: &str,
    ) -> Result<Option<Resolved>, SceneError> {
        match self.children_of(category).as_slice() {
            [] => Ok(None),
            [one] => Ok(Some(one.clone())),
            [_, second, ..] => Err(invalid(
                &second.loc,
                format!("{owner} has more than one {}", category.tag()),
            )),
        }
    }

    /// Error on the first property or nested object that no one consumed.
    pub(crate) fn finish(&self) -> Result<(), SceneError> {
        for (p, used) in self.node.props.iter().zip(self.used_props.borrow().iter()) {
            if !used {
                if let Value::CommandLine(text) = &p.value {
                    return Err(invalid(
                        &p.loc,
                        format!(
                            "-D {}={text}: the scene does not use ${} and {} has no parameter '{}'",
                            p.name,
                            p.name,
                            self.what(),
                            p.name
                        ),
                    ));
                }
                return Err(invalid(
                    &p.loc,
                    format!(
                        "unknown parameter '{}' (<{}>) for {}",
                        p.name,
                        p.value.type_name(),
                        self.what()
                    ),
                ));
            }
        }
        for (c, used) in self.children.iter().zip(self.used_children.borrow().iter()) {
            if !used {
                let name = c
                    .name
                    .as_ref()
                    .map(|n| format!(" named '{n}'"))
                    .unwrap_or_default();
                return Err(invalid(
                    &c.loc,
                    format!(
                        "unexpected nested {} {}{name} inside {}",
                        c.node.plugin,
                        c.node.category.tag(),
                        self.what()
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// Whether a keyword's words are compared as written or in lower case.
pub(crate) enum Case {
    /// As written (Mitsuba's default for string parameters).
    Sensitive,
    /// In lower case (where Mitsuba folds the case itself).
    Insensitive,
}

/// A parameter whose value is one of a fixed set of words, read by [`Props::keyword`].
pub(crate) trait Keyword: Copy + 'static {
    /// The words Mitsuba accepts, each with its value, in the order errors list them.
    const NAMES: &'static [(&'static str, Self)];
    /// How words are compared.
    const CASE: Case;
}

/// `keywords!(Type, Sensitive | Insensitive: "word" => value, ...)`: the [`Keyword`] table
/// of `Type`, its words compared as [`Case`] says.
macro_rules! keywords {
    ($t:ty, $case:ident: $($word:literal => $v:expr),+ $(,)?) => {
        impl $crate::props::Keyword for $t {
            const NAMES: &'static [(&'static str, Self)] = &[$(($word, $v)),+];
            const CASE: $crate::props::Case = $crate::props::Case::$case;
        }
    };
}
pub(crate) use keywords;
