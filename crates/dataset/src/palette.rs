//! The one palette of the project's pictures: object masks (contact sheets) and slot
//! segmentations (renders, reports) colour label k the same way.

/// Tableau 10: ten colours told apart easily, also by most colour-blind readers.
const TABLEAU_10: [[u8; 3]; 10] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
];

/// The colour of label `k` (a slot, an object; from 0), repeating after ten.
pub fn label_colour(k: u32) -> [u8; 3] {
    TABLEAU_10[k as usize % TABLEAU_10.len()]
}

/// The colour of an instance-mask id: 0 (background) is black, object `i` is label
/// `i − 1`'s colour.
pub fn instance_colour(id: u8) -> [u8; 3] {
    match id {
        0 => [0, 0, 0],
        i => label_colour(u32::from(i) - 1),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_repeat_after_ten_and_the_background_is_black() {
        assert_eq!(label_colour(13), label_colour(3));
        assert_ne!(label_colour(0), label_colour(1));
        assert_eq!(instance_colour(0), [0, 0, 0]);
        assert_eq!(instance_colour(1), label_colour(0));
        assert_eq!(instance_colour(255), label_colour(254));
    }
}
