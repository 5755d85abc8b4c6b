//! Integrator plugins. Each integrator type is one function from its
//! properties to an [`IntegratorDesc`]; add a new one by adding a match arm
//! in [`integrator`] and its function.

use crate::context::Ctx;
use crate::desc::{IntegratorDesc, PathParams};
use crate::error::SceneError;
use crate::props::{Props, Resolved};
use crate::xml::invalid;

/// Build the integrator `r`.
pub(crate) fn integrator(ctx: &Ctx, r: &Resolved) -> Result<IntegratorDesc, SceneError> {
    let p = ctx.props(&r.node)?;
    let desc = match p.plugin() {
        "path" => IntegratorDesc::Path(path_params(&p)?),
        other => {
            return Err(invalid(
                p.loc(),
                format!("unsupported integrator type '{other}' (supported: path)"),
            ))
        }
    };
    p.finish()?;
    Ok(desc)
}

/// Mitsuba's `path`: `max_depth` (-1 = unbounded), `rr_depth` (5, must be
/// > 0), `hide_emitters` (false).
fn path_params(p: &Props) -> Result<PathParams, SceneError> {
    let d = PathParams::default();
    Ok(PathParams {
        max_depth: p.int_in("max_depth", d.max_depth as i64, -1, i32::MAX as i64)? as i32,
        rr_depth: p.int_in("rr_depth", d.rr_depth as i64, 1, u32::MAX as i64)? as u32,
        hide_emitters: p.bool("hide_emitters", d.hide_emitters)?,
    })
}
