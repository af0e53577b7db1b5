//! The muxer: one H.264 track, all samples in one chunk.

fn put_box(out: &mut Vec<u8>, kind: &[u8; 4], body: &[u8]) {
    out.extend_from_slice(&((body.len() + 8) as u32).to_be_bytes());
    out.extend_from_slice(kind);
    out.extend_from_slice(body);
}

fn full_box(kind: &[u8; 4], version: u8, flags: u32, body: &[u8]) -> Vec<u8> {
    let mut b = Vec::with_capacity(body.len() + 4);
    b.push(version);
    b.extend_from_slice(&flags.to_be_bytes()[1..]);
    b.extend_from_slice(body);
    let mut out = Vec::new();
    put_box(&mut out, kind, &b);
    out
}

fn boxed(kind: &[u8; 4], body: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    put_box(&mut out, kind, body);
    out
}

const UNITY_MATRIX: [u32; 9] = [0x0001_0000, 0, 0, 0, 0x0001_0000, 0, 0, 0, 0x4000_0000];

/// An H.264 stream to mux.
#[derive(Debug, Clone, Copy)]
pub struct H264Stream<'a> {
    /// Width (pixels).
    pub width: u16,
    /// Height (pixels).
    pub height: u16,
    /// Media timescale (units per second).
    pub timescale: u32,
    /// Duration of every sample (timescale units).
    pub sample_duration: u32,
    /// Sequence parameter set (NAL unit without start code).
    pub sps: &'a [u8],
    /// Picture parameter set.
    pub pps: &'a [u8],
    /// Samples: length-prefixed (4-byte) NAL units.
    pub samples: &'a [Vec<u8>],
    /// `sync[i]`: sample `i` is an IDR picture.
    pub sync: &'a [bool],
}

/// Serialises an MP4 file holding `stream`.
pub fn mux_h264(stream: &H264Stream<'_>) -> Vec<u8> {
    let H264Stream {
        width,
        height,
        timescale,
        sample_duration: duration,
        sps,
        pps,
        samples,
        sync,
    } = *stream;
    let n = samples.len() as u32;
    let total = u64::from(n) * u64::from(duration);
    let mut out = Vec::new();
    let mut ftyp = Vec::new();
    ftyp.extend_from_slice(b"isom");
    ftyp.extend_from_slice(&512u32.to_be_bytes());
    for b in [b"isom", b"iso2", b"avc1", b"mp41"] {
        ftyp.extend_from_slice(b);
    }
    put_box(&mut out, b"ftyp", &ftyp);
    let data_len: u64 = samples.iter().map(|s| s.len() as u64).sum();
    if data_len + 8 <= u64::from(u32::MAX) {
        out.extend_from_slice(&((data_len + 8) as u32).to_be_bytes());
        out.extend_from_slice(b"mdat");
    } else {
        out.extend_from_slice(&1u32.to_be_bytes());
        out.extend_from_slice(b"mdat");
        out.extend_from_slice(&(data_len + 16).to_be_bytes());
    }
    let data_offset = out.len() as u64;
    for s in samples {
        out.extend_from_slice(s);
    }

    // moov
    let mut mvhd = Vec::new();
    mvhd.extend_from_slice(&[0; 8]); // creation, modification
    mvhd.extend_from_slice(&timescale.to_be_bytes());
    mvhd.extend_from_slice(&(total.min(u64::from(u32::MAX)) as u32).to_be_bytes());
    mvhd.extend_from_slice(&0x0001_0000u32.to_be_bytes()); // rate 1.0
    mvhd.extend_from_slice(&0x0100u16.to_be_bytes()); // volume 1.0
    mvhd.extend_from_slice(&[0; 10]);
    for m in UNITY_MATRIX {
        mvhd.extend_from_slice(&m.to_be_bytes());
    }
    mvhd.extend_from_slice(&[0; 24]);
    mvhd.extend_from_slice(&2u32.to_be_bytes()); // next track id

    let mut tkhd = Vec::new();
    tkhd.extend_from_slice(&[0; 8]);
    tkhd.extend_from_slice(&1u32.to_be_bytes());
    tkhd.extend_from_slice(&[0; 4]);
    tkhd.extend_from_slice(&(total.min(u64::from(u32::MAX)) as u32).to_be_bytes());
    tkhd.extend_from_slice(&[0; 8]);
    tkhd.extend_from_slice(&[0; 4]); // layer, alternate group
    tkhd.extend_from_slice(&[0; 4]); // volume, reserved
    for m in UNITY_MATRIX {
        tkhd.extend_from_slice(&m.to_be_bytes());
    }
    tkhd.extend_from_slice(&(u32::from(width) << 16).to_be_bytes());
    tkhd.extend_from_slice(&(u32::from(height) << 16).to_be_bytes());

    let mut mdhd = Vec::new();
    mdhd.extend_from_slice(&[0; 8]);
    mdhd.extend_from_slice(&timescale.to_be_bytes());
    mdhd.extend_from_slice(&(total.min(u64::from(u32::MAX)) as u32).to_be_bytes());
    mdhd.extend_from_slice(&0x55C4u16.to_be_bytes()); // "und"
    mdhd.extend_from_slice(&[0; 2]);

    let mut hdlr = Vec::new();
    hdlr.extend_from_slice(&[0; 4]);
    hdlr.extend_from_slice(b"vide");
    hdlr.extend_from_slice(&[0; 12]);
    hdlr.extend_from_slice(b"VideoHandler\0");

    let mut avcc = vec![
        1,
        sps.get(1).copied().unwrap_or(66),
        sps.get(2).copied().unwrap_or(0),
        sps.get(3).copied().unwrap_or(30),
        0xFF,
        0xE1,
    ];
    avcc.extend_from_slice(&(sps.len() as u16).to_be_bytes());
    avcc.extend_from_slice(sps);
    avcc.push(1);
    avcc.extend_from_slice(&(pps.len() as u16).to_be_bytes());
    avcc.extend_from_slice(pps);

    let mut avc1 = Vec::new();
    avc1.extend_from_slice(&[0; 6]);
    avc1.extend_from_slice(&1u16.to_be_bytes());
    avc1.extend_from_slice(&[0; 16]);
    avc1.extend_from_slice(&width.to_be_bytes());
    avc1.extend_from_slice(&height.to_be_bytes());
    avc1.extend_from_slice(&0x0048_0000u32.to_be_bytes());
    avc1.extend_from_slice(&0x0048_0000u32.to_be_bytes());
    avc1.extend_from_slice(&[0; 4]);
    avc1.extend_from_slice(&1u16.to_be_bytes());
    avc1.extend_from_slice(&[0; 32]);
    avc1.extend_from_slice(&0x0018u16.to_be_bytes());
    avc1.extend_from_slice(&0xFFFFu16.to_be_bytes());
    avc1.extend_from_slice(&boxed(b"avcC", &avcc));

    let mut stsd = 1u32.to_be_bytes().to_vec();
    stsd.extend_from_slice(&boxed(b"avc1", &avc1));
    let mut stts = 1u32.to_be_bytes().to_vec();
    stts.extend_from_slice(&n.to_be_bytes());
    stts.extend_from_slice(&duration.to_be_bytes());
    let sync_ids: Vec<u32> = (0..n)
        .filter(|&i| sync.get(i as usize).copied().unwrap_or(false))
        .map(|i| i + 1)
        .collect();
    let mut stss = (sync_ids.len() as u32).to_be_bytes().to_vec();
    for i in &sync_ids {
        stss.extend_from_slice(&i.to_be_bytes());
    }
    let mut stsc = 1u32.to_be_bytes().to_vec();
    for v in [1u32, n, 1] {
        stsc.extend_from_slice(&v.to_be_bytes());
    }
    let mut stsz = 0u32.to_be_bytes().to_vec();
    stsz.extend_from_slice(&n.to_be_bytes());
    for s in samples {
        stsz.extend_from_slice(&(s.len() as u32).to_be_bytes());
    }
    let chunk_box = if data_offset <= u64::from(u32::MAX) {
        let mut b = 1u32.to_be_bytes().to_vec();
        b.extend_from_slice(&(data_offset as u32).to_be_bytes());
        full_box(b"stco", 0, 0, &b)
    } else {
        let mut b = 1u32.to_be_bytes().to_vec();
        b.extend_from_slice(&data_offset.to_be_bytes());
        full_box(b"co64", 0, 0, &b)
    };
    let mut stbl = Vec::new();
    stbl.extend_from_slice(&full_box(b"stsd", 0, 0, &stsd));
    stbl.extend_from_slice(&full_box(b"stts", 0, 0, &stts));
    stbl.extend_from_slice(&full_box(b"stss", 0, 0, &stss));
    stbl.extend_from_slice(&full_box(b"stsc", 0, 0, &stsc));
    stbl.extend_from_slice(&full_box(b"stsz", 0, 0, &stsz));
    stbl.extend_from_slice(&chunk_box);

    let mut dref = 1u32.to_be_bytes().to_vec();
    dref.extend_from_slice(&full_box(b"url ", 0, 1, &[]));
    let dinf = boxed(b"dinf", &full_box(b"dref", 0, 0, &dref));
    let mut minf = full_box(b"vmhd", 0, 1, &[0; 8]);
    minf.extend_from_slice(&dinf);
    minf.extend_from_slice(&boxed(b"stbl", &stbl));
    let mut mdia = full_box(b"mdhd", 0, 0, &mdhd);
    mdia.extend_from_slice(&full_box(b"hdlr", 0, 0, &hdlr));
    mdia.extend_from_slice(&boxed(b"minf", &minf));
    let mut trak = full_box(b"tkhd", 0, 3, &tkhd);
    trak.extend_from_slice(&boxed(b"mdia", &mdia));
    let mut moov = full_box(b"mvhd", 0, 0, &mvhd);
    moov.extend_from_slice(&boxed(b"trak", &trak));
    put_box(&mut out, b"moov", &moov);
    out
}
