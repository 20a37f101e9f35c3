//! Number fields that never change what is typed: egui's range would clamp a typed value
//! without a word, so a value outside its range is kept, named in a note with its range,
//! and its action stays disabled until it is fixed.

use eframe::egui;
use eframe::egui::emath::Numeric;

/// A labelled number field (`label`, then the value) for `value`, allowed in `range`
/// (inclusive). Returns whether the value is allowed; if not, a note naming the field, the
/// value and the range is pushed to `notes` (shown under the fields by the caller).
pub(crate) fn number_field<T: Numeric + std::fmt::Display>(
    ui: &mut egui::Ui,
    label: &str,
    value: &mut T,
    range: (T, T),
    speed: f64,
    notes: &mut Vec<String>,
) -> bool {
    let l = ui.label(label);
    let r = ui
        .add(egui::DragValue::new(value).speed(speed))
        .labelled_by(l.id);
    crate::state_report::place(ui, label, &r);
    let v = value.to_f64();
    let ok = v.is_finite() && v >= range.0.to_f64() && v <= range.1.to_f64();
    if !ok {
        notes.push(out_of_range(label, *value, range));
    }
    ok
}

/// The note of a value outside its range.
pub(crate) fn out_of_range<T: std::fmt::Display>(label: &str, value: T, range: (T, T)) -> String {
    format!(
        "{label} = {value} is outside the allowed range [{}, {}]: not applied",
        range.0, range.1
    )
}

/// Shows `notes` in the error colour.
pub(crate) fn show_notes(ui: &mut egui::Ui, notes: &[String]) {
    for n in notes {
        let r = ui.colored_label(ui.visuals().error_fg_color, n.as_str());
        crate::state_report::place(ui, &format!("note: {n}"), &r);
    }
}
