//! The coordinator's web page (`web/page.html`): the job list updated in place from server-sent
//! events, a submit form, a page per job (zoomable preview with exposure, per-tile noise heat map,
//! error-over-time chart, settings, warnings, events, frames; cancel, resubmit, delete, download)
//! and the workers with drain/resume. Plain HTML and JavaScript against the REST API; the token
//! (if the farm has one) is kept in the browser's localStorage.

pub const PAGE: &str = include_str!("web/page.html");
