//! Colours: one per robot, for any number of robots.

use plotters::style::RGBColor;

/// An 8-bit RGB colour.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rgb(pub u8, pub u8, pub u8);

impl Rgb {
    /// White.
    pub const WHITE: Rgb = Rgb(255, 255, 255);
    /// Black.
    pub const BLACK: Rgb = Rgb(0, 0, 0);

    /// This colour mixed with white: `amount` 0 gives white, 1 the colour itself.
    pub fn tint(self, amount: f64) -> Rgb {
        let a = amount.clamp(0.0, 1.0);
        let mix = |c: u8| (255.0 - (255.0 - f64::from(c)) * a).round() as u8;
        Rgb(mix(self.0), mix(self.1), mix(self.2))
    }

    /// This colour scaled towards black by `factor` (1 keeps it).
    pub fn shade(self, factor: f64) -> Rgb {
        let f = factor.clamp(0.0, 1.0);
        let mix = |c: u8| (f64::from(c) * f).round() as u8;
        Rgb(mix(self.0), mix(self.1), mix(self.2))
    }

    /// Whether this colour lies on the way from white to `colour` (some `colour.tint(a)` with `a`
    /// above 0.1, within rounding), e.g. a map pixel of that robot. For reading pictures back.
    pub fn is_tint_of(self, colour: Rgb) -> bool {
        let pairs = [(self.0, colour.0), (self.1, colour.1), (self.2, colour.2)];
        // A channel at 255 in the colour stays 255 in every tint and tells nothing more.
        if pairs.iter().any(|&(p, c)| c == 255 && p != 255) {
            return false;
        }
        let amounts =
            pairs.iter().filter(|&&(_, c)| c < 255).map(|&(p, c)| (255.0 - f64::from(p)) / (255.0 - f64::from(c)));
        let (lo, hi) = amounts.fold((f64::INFINITY, 0.0f64), |(lo, hi), a| (lo.min(a), hi.max(a)));
        hi > 0.1 && hi - lo < 0.05
    }

    pub(crate) fn plotters(self) -> RGBColor {
        RGBColor(self.0, self.1, self.2)
    }
}

/// Robot colours: a fixed list, then hues spread by the golden angle for robots beyond it.
#[derive(Clone, Debug, PartialEq)]
pub struct Palette {
    /// The first colours, in order (default: Tableau 10 without its grey, which reads as "no
    /// robot" on a map).
    pub colours: Vec<Rgb>,
}

impl Default for Palette {
    fn default() -> Self {
        Palette {
            colours: vec![
                Rgb(31, 119, 180),
                Rgb(255, 127, 14),
                Rgb(44, 160, 44),
                Rgb(214, 39, 40),
                Rgb(148, 103, 189),
                Rgb(140, 86, 75),
                Rgb(227, 119, 194),
                Rgb(188, 189, 34),
                Rgb(23, 190, 207),
            ],
        }
    }
}

impl Palette {
    /// The colour of the `i`-th robot (0-based); distinct for any `i`.
    pub fn colour(&self, i: usize) -> Rgb {
        match self.colours.get(i) {
            Some(&c) => c,
            None => golden_hue(i - self.colours.len()),
        }
    }
}

/// Hue `k` of a sequence that never repeats and keeps neighbours far apart on the colour wheel.
fn golden_hue(k: usize) -> Rgb {
    const GOLDEN_TURN: f64 = 0.618_033_988_75;
    let hue = (0.07 + k as f64 * GOLDEN_TURN).fract() * 6.0;
    // Saturation 0.75, value 0.8: dark enough for lines on white, light enough to tint a map.
    let (s, v) = (0.75, 0.8);
    let c = v * s;
    let x = c * (1.0 - ((hue % 2.0) - 1.0).abs());
    let (r, g, b) = match hue as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    let byte = |u: f64| ((u + m) * 255.0).round() as u8;
    Rgb(byte(r), byte(g), byte(b))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colours_are_distinct_past_the_fixed_list() {
        let p = Palette::default();
        let all: Vec<Rgb> = (0..40).map(|i| p.colour(i)).collect();
        for (i, a) in all.iter().enumerate() {
            for b in &all[i + 1..] {
                assert_ne!(a, b);
            }
        }
    }

    #[test]
    fn tint_runs_from_white_to_the_colour() {
        let c = Rgb(31, 119, 180);
        assert_eq!(c.tint(0.0), Rgb::WHITE);
        assert_eq!(c.tint(1.0), c);
        assert_eq!(c.shade(0.5), Rgb(16, 60, 90));
    }

    #[test]
    fn tints_are_recognised_and_other_colours_are_not() {
        let (blue, orange) = (Rgb(31, 119, 180), Rgb(255, 127, 14));
        for a in [0.25, 0.5, 0.75, 1.0] {
            assert!(blue.tint(a).is_tint_of(blue) && orange.tint(a).is_tint_of(orange));
            assert!(!blue.tint(a).is_tint_of(orange) && !orange.tint(a).is_tint_of(blue));
        }
        assert!(!Rgb::WHITE.is_tint_of(blue));
        assert!(!Rgb(200, 200, 200).is_tint_of(blue));
    }
}
