//! Where things lie in an Ouster lidar packet, per UDP profile (`udp_profile_lidar`).
//!
//! LEGACY packets are a run of columns, each with its own header (timestamp, measurement id, frame
//! id, encoder count), pixels and a trailing status word. The other profiles put a 32-byte packet
//! header (packet type, frame id, init id, serial number, countdowns) before the columns and a
//! 32-byte footer after them; their column header holds the timestamp, measurement id and status.
//! All fields are little-endian.

/// The lidar packet layout the sensor was configured with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Profile {
    /// The firmware 1.x / 2.x default: 12-byte pixels, 20-bit range, 16-bit reflectivity.
    Legacy,
    /// Single return: 12-byte pixels, 19-bit range, 8-bit reflectivity.
    Rng19Rfl8Sig16Nir16,
    /// Dual return: 16-byte pixels, two ranges and two reflectivities.
    Rng19Rfl8Sig16Nir16Dual,
    /// Low data rate: 4-byte pixels, 15-bit range in units of 8 mm, 8-bit reflectivity.
    Rng15Rfl8Nir8,
}

impl Profile {
    /// All the profiles this decoder reads.
    pub const ALL: [Profile; 4] =
        [Profile::Legacy, Profile::Rng19Rfl8Sig16Nir16, Profile::Rng19Rfl8Sig16Nir16Dual, Profile::Rng15Rfl8Nir8];

    /// The profile a metadata's `udp_profile_lidar` names.
    pub fn from_name(name: &str) -> Option<Profile> {
        Profile::ALL.into_iter().find(|profile| profile.name() == name)
    }

    /// The name the metadata uses.
    pub fn name(self) -> &'static str {
        match self {
            Profile::Legacy => "LEGACY",
            Profile::Rng19Rfl8Sig16Nir16 => "RNG19_RFL8_SIG16_NIR16",
            Profile::Rng19Rfl8Sig16Nir16Dual => "RNG19_RFL8_SIG16_NIR16_DUAL",
            Profile::Rng15Rfl8Nir8 => "RNG15_RFL8_NIR8",
        }
    }

    /// Whether each pixel carries a second return.
    pub fn is_dual(self) -> bool {
        self == Profile::Rng19Rfl8Sig16Nir16Dual
    }

    /// Bytes of one pixel (one beam of one column).
    pub fn pixel_bytes(self) -> usize {
        match self {
            Profile::Legacy | Profile::Rng19Rfl8Sig16Nir16 => 12,
            Profile::Rng19Rfl8Sig16Nir16Dual => 16,
            Profile::Rng15Rfl8Nir8 => 4,
        }
    }

    /// Bytes of one lidar packet (saturating, so that absurd metadata gives a size no payload has).
    pub fn lidar_packet_bytes(self, pixels_per_column: usize, columns_per_packet: usize) -> usize {
        PacketFormat::new(self, pixels_per_column, columns_per_packet).packet_bytes()
    }
}

/// The size of a LEGACY IMU packet, which carries no points.
pub(super) const LEGACY_IMU_PACKET_BYTES: usize = 48;

/// The non-LEGACY packet header's `packet_type` of a lidar data packet.
const LIDAR_PACKET_TYPE: u16 = 1;
const PACKET_HEADER_BYTES: usize = 32;
const PACKET_FOOTER_BYTES: usize = 32;
const LEGACY_COLUMN_HEADER_BYTES: usize = 16;
const LEGACY_COLUMN_STATUS_BYTES: usize = 4;
const COLUMN_HEADER_BYTES: usize = 12;

/// One profile at one sensor size: the packet's geometry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct PacketFormat {
    pub profile: Profile,
    pub pixels_per_column: usize,
    pub columns_per_packet: usize,
}

/// What the packet header says (LEGACY has none: its frame id is in each column).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct PacketHeader {
    pub frame_id: Option<u16>,
    /// Changes when the sensor re-initialises; `None` for LEGACY.
    pub init_id: Option<u32>,
}

/// One column (one firing of all beams) of a packet.
#[derive(Clone, Copy, Debug)]
pub(super) struct Column<'a> {
    pub timestamp_ns: u64,
    /// The column's index within the frame, 0 at the encoder's zero.
    pub measurement_id: u16,
    /// LEGACY only: the frame the column belongs to.
    pub frame_id: Option<u16>,
    /// The status word's bit 0, as ouster-sdk tests it (LEGACY sends all ones when valid).
    pub valid: bool,
    pub pixels: &'a [u8],
}

/// One return of one beam: range in millimetres (0: no return) and calibrated reflectivity.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct Echo {
    pub range_mm: u32,
    pub reflectivity: u16,
}

/// What one pixel reports: its first (strongest) return, and the second of a dual profile.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct Pixel {
    pub first: Echo,
    pub second: Option<Echo>,
}

impl PacketFormat {
    pub fn new(profile: Profile, pixels_per_column: usize, columns_per_packet: usize) -> PacketFormat {
        PacketFormat { profile, pixels_per_column, columns_per_packet }
    }

    fn legacy(&self) -> bool {
        self.profile == Profile::Legacy
    }

    fn column_header_bytes(&self) -> usize {
        if self.legacy() { LEGACY_COLUMN_HEADER_BYTES } else { COLUMN_HEADER_BYTES }
    }

    fn pixels_bytes(&self) -> usize {
        self.pixels_per_column.saturating_mul(self.profile.pixel_bytes())
    }

    fn column_bytes(&self) -> usize {
        let status = if self.legacy() { LEGACY_COLUMN_STATUS_BYTES } else { 0 };
        self.column_header_bytes().saturating_add(self.pixels_bytes()).saturating_add(status)
    }

    fn packet_header_bytes(&self) -> usize {
        if self.legacy() { 0 } else { PACKET_HEADER_BYTES }
    }

    pub fn packet_bytes(&self) -> usize {
        let footer = if self.legacy() { 0 } else { PACKET_FOOTER_BYTES };
        self.columns_per_packet.saturating_mul(self.column_bytes()).saturating_add(self.packet_header_bytes() + footer)
    }

    /// The packet header of a payload of [`PacketFormat::packet_bytes`]; an error names a packet
    /// type other than lidar data.
    pub fn header(&self, packet: &[u8]) -> Result<PacketHeader, String> {
        if self.legacy() {
            return Ok(PacketHeader { frame_id: None, init_id: None });
        }
        let packet_type = read_u16(packet, 0);
        if packet_type != LIDAR_PACKET_TYPE {
            return Err(format!("packet_type {packet_type} is not lidar data ({LIDAR_PACKET_TYPE})"));
        }
        // init_id is the 24 bits at bytes 4..7.
        let init_id = read_u32(packet, 4) & 0x00ff_ffff;
        Ok(PacketHeader { frame_id: Some(read_u16(packet, 2)), init_id: Some(init_id) })
    }

    /// The packet's columns, in the order sent.
    pub fn columns<'a>(&self, packet: &'a [u8]) -> impl Iterator<Item = Column<'a>> {
        let start = self.packet_header_bytes();
        let end = start.saturating_add(self.columns_per_packet.saturating_mul(self.column_bytes()));
        let body = packet.get(start..end).unwrap_or_default();
        let format = *self;
        // `max(1)`: chunks_exact refuses a zero size, which only absurd metadata could give.
        body.chunks_exact(self.column_bytes().max(1)).map(move |bytes| format.column(bytes))
    }

    fn column<'a>(&self, bytes: &'a [u8]) -> Column<'a> {
        let pixels_start = self.column_header_bytes();
        let pixels_end = pixels_start.saturating_add(self.pixels_bytes());
        let pixels = bytes.get(pixels_start..pixels_end).unwrap_or_default();
        let (frame_id, status) = if self.legacy() {
            (Some(read_u16(bytes, 10)), read_u32(bytes, pixels_end))
        } else {
            (None, u32::from(read_u16(bytes, 10)))
        };
        Column {
            timestamp_ns: read_u64(bytes, 0),
            measurement_id: read_u16(bytes, 8),
            frame_id,
            valid: status & 1 == 1,
            pixels,
        }
    }

    /// The column's pixels, one per beam from the metadata's first beam.
    pub fn pixels<'a>(&self, column: &Column<'a>) -> impl Iterator<Item = Pixel> + 'a {
        let profile = self.profile;
        column.pixels.chunks_exact(profile.pixel_bytes()).map(move |bytes| pixel(profile, bytes))
    }
}

fn pixel(profile: Profile, bytes: &[u8]) -> Pixel {
    match profile {
        Profile::Legacy => Pixel {
            first: Echo { range_mm: read_u32(bytes, 0) & 0x000f_ffff, reflectivity: read_u16(bytes, 4) },
            second: None,
        },
        Profile::Rng19Rfl8Sig16Nir16 => Pixel {
            first: Echo { range_mm: read_u32(bytes, 0) & 0x0007_ffff, reflectivity: read_u8(bytes, 4).into() },
            second: None,
        },
        Profile::Rng19Rfl8Sig16Nir16Dual => Pixel {
            first: Echo { range_mm: read_u32(bytes, 0) & 0x0007_ffff, reflectivity: read_u8(bytes, 3).into() },
            second: Some(Echo { range_mm: read_u32(bytes, 4) & 0x0007_ffff, reflectivity: read_u8(bytes, 7).into() }),
        },
        // The 15-bit range counts units of 8 mm.
        Profile::Rng15Rfl8Nir8 => Pixel {
            first: Echo {
                range_mm: u32::from(read_u16(bytes, 0) & 0x7fff) << 3,
                reflectivity: read_u8(bytes, 2).into(),
            },
            second: None,
        },
    }
}

// Readers of little-endian fields. The payload's length is checked against the layout before any
// field is read, so every read is in bounds; a read past the end gives zero rather than a panic.

fn read_bytes<const N: usize>(bytes: &[u8], at: usize) -> [u8; N] {
    at.checked_add(N)
        .and_then(|end| bytes.get(at..end))
        .and_then(|slice| <[u8; N]>::try_from(slice).ok())
        .unwrap_or([0; N])
}

fn read_u8(bytes: &[u8], at: usize) -> u8 {
    bytes.get(at).copied().unwrap_or(0)
}

fn read_u16(bytes: &[u8], at: usize) -> u16 {
    u16::from_le_bytes(read_bytes(bytes, at))
}

fn read_u32(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(read_bytes(bytes, at))
}

fn read_u64(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(read_bytes(bytes, at))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packet_sizes_match_the_sensor_documentation() {
        assert_eq!(Profile::Legacy.lidar_packet_bytes(32, 16), 6464);
        assert_eq!(Profile::Legacy.lidar_packet_bytes(64, 16), 12608);
        assert_eq!(Profile::Rng19Rfl8Sig16Nir16.lidar_packet_bytes(128, 16), 24832);
        assert_eq!(Profile::Rng19Rfl8Sig16Nir16Dual.lidar_packet_bytes(128, 16), 33024);
        assert_eq!(Profile::Rng15Rfl8Nir8.lidar_packet_bytes(128, 16), 8448);
    }

    #[test]
    fn profile_names_round_trip() {
        for profile in Profile::ALL {
            assert_eq!(Profile::from_name(profile.name()), Some(profile));
        }
        assert_eq!(Profile::from_name("FUSA_RNG15_RFL8_NIR8_DUAL"), None);
    }

    #[test]
    fn low_data_range_is_in_units_of_8_mm() {
        let got = pixel(Profile::Rng15Rfl8Nir8, &[0x01, 0x80, 77, 9]);
        assert_eq!(got.first, Echo { range_mm: 8, reflectivity: 77 });
    }

    #[test]
    fn short_reads_give_zero() {
        assert_eq!(read_u32(&[1, 2], 0), 0);
        assert_eq!(read_u64(&[], usize::MAX), 0);
    }
}
