//! Minimal KTX2 and DDS files of given levels: the containers [`crate::library`] decodes,
//! written for the tests and the fuzz harness's seeds.

/// A KTX2 file of `levels` (finest first): header, level index, a 4-byte data format
/// descriptor, then the levels in order. The minimal writer behind the fuzz seeds and the
/// tests' KTX2 files.
pub fn ktx2_file(vk_format: u32, width: u32, height: u32, levels: &[Vec<u8>]) -> Vec<u8> {
    let mut f = vec![0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A];
    for v in [vk_format, 1, width, height, 0, 0, 1, levels.len() as u32, 0] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    let dfd_offset = 80 + 24 * levels.len();
    for v in [dfd_offset as u32, 4, 0, 0] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    // No supercompression global data.
    f.extend_from_slice(&[0u8; 16]);
    let mut offset = (dfd_offset + 4) as u64;
    for level in levels {
        for v in [offset, level.len() as u64, level.len() as u64] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        offset += level.len() as u64;
    }
    f.extend_from_slice(&4u32.to_le_bytes());
    for level in levels {
        f.extend_from_slice(level);
    }
    f
}

/// A DDS file of `levels` (finest first) with the FourCC `four_cc`; `DX10` adds the extended
/// header naming `dxgi_format` (ignored otherwise). The minimal writer behind the fuzz seeds
/// and the tests' DDS files.
pub fn dds_file(four_cc: &[u8; 4], dxgi_format: u32, width: u32, height: u32, levels: &[Vec<u8>]) -> Vec<u8> {
    const DDSD_MIPMAPCOUNT: u32 = 0x2_0000;
    const CAPS_MIPMAP: u32 = 0x40_0008;
    let mipmapped = levels.len() > 1;
    let flags = 0x1007 | if mipmapped { DDSD_MIPMAPCOUNT } else { 0 };
    let mut dds = b"DDS ".to_vec();
    // size, flags (caps|height|width|pixelformat[|mipmapcount]), height, width, linear size,
    // depth, mip count
    let linear_size = levels.first().map_or(0, Vec::len) as u32;
    for v in [124u32, flags, height, width, linear_size, 0, levels.len() as u32] {
        dds.extend_from_slice(&v.to_le_bytes());
    }
    dds.extend_from_slice(&[0u8; 44]);
    for v in [32u32, 0x4] {
        dds.extend_from_slice(&v.to_le_bytes());
    }
    dds.extend_from_slice(four_cc);
    dds.extend_from_slice(&[0u8; 20]);
    let caps = 0x1000 | if mipmapped { CAPS_MIPMAP } else { 0 };
    dds.extend_from_slice(&caps.to_le_bytes());
    dds.extend_from_slice(&[0u8; 16]);
    if four_cc == b"DX10" {
        // DXGI format, dimension (TEXTURE2D), misc flags, array size, misc flags 2.
        for v in [dxgi_format, 3, 0, 1, 0] {
            dds.extend_from_slice(&v.to_le_bytes());
        }
    }
    for level in levels {
        dds.extend_from_slice(level);
    }
    dds
}
