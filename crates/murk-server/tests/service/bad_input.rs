//! Bad input gets INVALID_ARGUMENT naming the field, and the server keeps serving.

use crate::common;

use common::*;
use murk_server::service::proto::v1 as pb;
use prost::Message;
use tonic::Code;
use tonic_types::StatusExt;

fn raw(width: u32, height: u32, values: &[f32]) -> pb::Image {
    pb::Image {
        width,
        height,
        channels: 1,
        data: Some(pb::image::Data::RawF32Le(
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )),
        value_scale: 0.0,
        value_offset: 0.0,
        transfer: 0,
    }
}

fn encoded(bytes: Vec<u8>) -> pb::Image {
    pb::Image {
        data: Some(pb::image::Data::Encoded(bytes)),
        ..Default::default()
    }
}

async fn submit_err(
    server: &murk_server::server::InProcessServer,
    req: pb::TofDepthRequest,
) -> String {
    let s = jobs(server).submit_job(job(req)).await.unwrap_err();
    bad_field(&s)
}

#[tokio::test]
async fn bad_tof_requests_name_the_field_and_the_server_keeps_serving() {
    let server = start(config(4)).await;
    let good = tof_request(48, 40, 11);

    let mut r = good.clone();
    r.phase = Some(raw(40, 48, &vec![1.0; 40 * 48]));
    assert_eq!(submit_err(&server, r).await, "request.tof_depth.phase");

    let mut r = good.clone();
    let mut v = vec![1.0f32; 48 * 40];
    v[100] = f32::NAN;
    r.amplitude = Some(raw(48, 40, &v));
    assert_eq!(submit_err(&server, r).await, "request.tof_depth.amplitude");

    // Finite, but beyond what the solver computes with: INVALID_ARGUMENT, not INTERNAL.
    let mut r = good.clone();
    r.amplitude.as_mut().unwrap().value_scale = 1e20;
    assert_eq!(submit_err(&server, r).await, "request.tof_depth.amplitude");
    let mut r = good.clone();
    let mut v = vec![1.0f32; 48 * 40];
    v[100] = 1e33;
    r.amplitude = Some(raw(48, 40, &v));
    assert_eq!(submit_err(&server, r).await, "request.tof_depth.amplitude");
    let mut r = good.clone();
    r.amplitude = Some(raw(48, 40, &vec![1e-45; 48 * 40]));
    assert_eq!(submit_err(&server, r).await, "request.tof_depth.amplitude");

    let mut r = good.clone();
    r.amplitude = Some(raw(0, 40, &[]));
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.amplitude.width"
    );

    let mut r = good.clone();
    r.amplitude = Some(encoded(b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR garbage".to_vec()));
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.amplitude.encoded"
    );

    let mut r = good.clone();
    // OpenEXR magic followed by a truncated header.
    r.phase = Some(encoded(vec![
        0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0, b'c', b'h',
    ]));
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.phase.encoded"
    );

    let mut r = good.clone();
    r.amplitude = Some(encoded(vec![1, 2, 3, 4, 5]));
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.amplitude.encoded"
    );

    for f in [0.0, -16e6, f64::NAN, f64::INFINITY] {
        let mut r = good.clone();
        r.modulation_frequency_hz = f;
        assert_eq!(
            submit_err(&server, r).await,
            "request.tof_depth.modulation_frequency_hz"
        );
    }

    let mut r = good.clone();
    r.amplitude = None;
    assert_eq!(submit_err(&server, r).await, "request.tof_depth.amplitude");

    let mut r = good.clone();
    r.intrinsics = Some(pb::CameraIntrinsics {
        fx: -1.0,
        fy: 1.0,
        cx: 0.0,
        cy: 0.0,
        skew: 0.0,
    });
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.intrinsics.fx"
    );

    let mut r = good.clone();
    r.options = Some(pb::TofOptions {
        fine_iterations: Some(u32::MAX),
        ..Default::default()
    });
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.options.fine_iterations"
    );

    let mut r = good.clone();
    r.options = Some(pb::TofOptions {
        patches_x: Some(0),
        ..Default::default()
    });
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.options.patches_x"
    );

    let mut r = good.clone();
    r.options = Some(pb::TofOptions {
        amplitude: Some(pb::IrlsOptions {
            gamma_smoothness: Some(-1.0),
            ..Default::default()
        }),
        ..Default::default()
    });
    assert_eq!(
        submit_err(&server, r).await,
        "request.tof_depth.options.amplitude.gamma_smoothness"
    );

    for (options, field) in [
        (
            pb::TofOptions {
                channels: 99,
                ..Default::default()
            },
            "request.tof_depth.options.channels",
        ),
        (
            pb::TofOptions {
                coarse_quantile: Some(1.5),
                ..Default::default()
            },
            "request.tof_depth.options.coarse_quantile",
        ),
        (
            pb::TofOptions {
                coarse_subdivision: Some(0),
                ..Default::default()
            },
            "request.tof_depth.options.coarse_subdivision",
        ),
        (
            pb::TofOptions {
                phasor: Some(pb::IrlsOptions {
                    c_fine: Some(0.0),
                    ..Default::default()
                }),
                ..Default::default()
            },
            "request.tof_depth.options.phasor.c_fine",
        ),
    ] {
        let mut r = good.clone();
        r.options = Some(options);
        assert_eq!(submit_err(&server, r).await, field);
    }

    let e = jobs(&server)
        .submit_job(pb::SubmitJobRequest {
            request: None,
            omit_result: false,
        })
        .await
        .unwrap_err();
    assert_eq!(bad_field(&e), "request");

    // The unary RPC names fields relative to its own request message.
    let mut r = good.clone();
    r.modulation_frequency_hz = 0.0;
    let e = recon(&server).tof_depth(r).await.unwrap_err();
    assert_eq!(bad_field(&e), "modulation_frequency_hz");

    // Still serving: a good request succeeds.
    let ok = recon(&server).tof_depth(good).await.unwrap().into_inner();
    assert!(ok.range_m.is_some());
    server.stop().await.unwrap();
}

#[tokio::test]
async fn every_request_over_the_limit_gets_resource_exhausted_unknown_fields_included() {
    const LIMIT: usize = 256 * 1024;
    let mut cfg = config(4);
    cfg.max_request_bytes = LIMIT;
    let server = start(cfg).await;
    let over = |s: &tonic::Status| {
        assert_eq!(s.code(), Code::ResourceExhausted, "{s:?}");
        assert!(s.message().contains(&format!("{LIMIT} bytes")), "{s:?}");
        assert!(s.message().contains("--max-request-bytes"), "{s:?}");
        assert!(
            s.get_details_retry_info().is_none(),
            "the same request cannot succeed later: {s:?}"
        );
    };
    // Just over (≈ 320 KB of known fields) and far over (≈ 1.3 MB): one answer, whichever RPC.
    for side in [200, 400] {
        let mut r = tof_request(48, 40, 2);
        r.amplitude = Some(raw(side, side, &vec![1.0; (side * side) as usize]));
        r.phase = Some(raw(side, side, &vec![1.0; (side * side) as usize]));
        over(&jobs(&server).submit_job(job(r.clone())).await.unwrap_err());
        over(&recon(&server).tof_depth(r).await.unwrap_err());
    }

    // A small request padded with an unknown field counts every byte: over the limit it is
    // refused like any other, under it the padding is ignored.
    let mut grpc = tonic::client::Grpc::new(channel(&server));
    let padded = |pad: usize| {
        let mut bytes = tof_request(48, 40, 2).encode_to_vec();
        // Field 1000, wire type 2 (length-delimited): unknown to the server.
        prost::encoding::encode_key(1000, prost::encoding::WireType::LengthDelimited, &mut bytes);
        prost::encoding::encode_varint(pad as u64, &mut bytes);
        bytes.resize(bytes.len() + pad, 0xAB);
        bytes
    };
    for (pad, refused) in [(LIMIT, true), (LIMIT / 4, false)] {
        grpc.ready().await.unwrap();
        let got = grpc
            .unary(
                tonic::Request::new(padded(pad)),
                http::uri::PathAndQuery::from_static("/murk.v1.Reconstruction/TofDepth"),
                RawCodec,
            )
            .await;
        match (got, refused) {
            (Err(s), true) => over(&s),
            (Ok(_), false) => {}
            (got, _) => panic!("padding {pad}: {got:?}"),
        }
    }

    // Compressed on the wire, over the limit once decompressed: the same answer.
    let mut r = tof_request(48, 40, 2);
    r.amplitude = Some(raw(400, 400, &vec![1.0; 400 * 400]));
    let s = recon(&server)
        .send_compressed(tonic::codec::CompressionEncoding::Gzip)
        .tof_depth(r)
        .await
        .unwrap_err();
    over(&s);

    let ok = recon(&server)
        .tof_depth(tof_request(48, 40, 2))
        .await
        .unwrap()
        .into_inner();
    assert!(ok.mask.is_some());
    server.stop().await.unwrap();
}

#[tokio::test]
async fn oversized_images_are_refused_before_allocation() {
    let mut cfg = config(4);
    cfg.max_image_pixels = 1000;
    let server = start(cfg).await;
    let r = tof_request(48, 40, 2); // 1920 px > 1000
    let field = submit_err(&server, r).await;
    assert_eq!(field, "request.tof_depth.amplitude.width");
    // A tiny PNG header that claims a gigantic image is refused without allocating it.
    let mut png = Vec::new();
    {
        let mut enc = png_header(60_000, 60_000);
        png.append(&mut enc);
    }
    let mut r = tof_request(48, 40, 2);
    r.amplitude = Some(encoded(png));
    let field = submit_err(&server, r).await;
    assert_eq!(field, "request.tof_depth.amplitude.encoded");
    server.stop().await.unwrap();
}

/// PNG signature + an IHDR chunk (valid CRC) claiming `w × h` 16-bit grey, and nothing else.
fn png_header(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[16, 0, 0, 0, 0]);
    out.extend_from_slice(&13u32.to_be_bytes());
    out.extend_from_slice(&ihdr);
    out.extend_from_slice(&crc32(&ihdr).to_be_bytes());
    out
}

fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}
