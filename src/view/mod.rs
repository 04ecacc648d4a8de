//! `acags view`: a local web page that plays a trained scene. The server holds the model and
//! answers four kinds of request, all generated in memory: the page, its script, the scene's
//! manifest and one frame as a standard 3DGS PLY ([`crate::export::frame_splats`], decoded on
//! first request and cached). It reads no file after start-up, so it cannot expose one.
//!
//! The renderer is our own small WebGL2 splatter (`assets/player/player.js`): it draws with the
//! rig's pinhole intrinsics and the conventions of acags' rasterizer (0.3 px² blur,
//! opacity-aware extent, α ≤ 0.999, α < 1/255 skipped), which the generic viewers on npm do not
//! take (they assume a centred principal point and a field of view), so the browser test can
//! hold the page to acags' own render. Nothing is fetched from anywhere but the server: the
//! page sets a Content-Security-Policy of 'self'.

use std::io::Cursor;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use anyhow::{Result, anyhow};
use serde::Serialize;
use tiny_http::{Header, Method, Request, Response, Server};

use crate::export::frame_splats;
use crate::io::camera_json::CameraFile;
use crate::io::splat_ply::splat_ply_bytes;
use crate::run::OpenedScene;

const INDEX_HTML: &str = include_str!("../../assets/player/index.html");
const PLAYER_JS: &str = include_str!("../../assets/player/player.js");

/// Frames kept decoded in memory (PLY bytes), oldest dropped first.
const CACHE_BYTES: usize = 1 << 30;

pub struct ViewOptions {
    pub bind: IpAddr,
    /// 0 picks a free port.
    pub port: u16,
    pub sh_degree: usize,
}

/// What a request path asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    Page,
    Script,
    Manifest,
    /// A dataset frame index.
    Frame(usize),
    NotFound,
}

/// Routes a request target (path and optional query). Only these exact paths exist: anything
/// else, `..` or encoded tricks included, is [`Route::NotFound`].
pub fn route(target: &str) -> Route {
    let path = target.split(['?', '#']).next().unwrap_or("");
    match path {
        "/" | "/index.html" => Route::Page,
        "/player.js" => Route::Script,
        "/scene.json" => Route::Manifest,
        _ => path
            .strip_prefix("/frames/")
            .and_then(|f| f.strip_suffix(".ply"))
            .filter(|n| !n.is_empty() && n.len() <= 9 && n.bytes().all(|b| b.is_ascii_digit()))
            .and_then(|n| n.parse().ok())
            .map_or(Route::NotFound, Route::Frame),
    }
}

#[derive(Serialize)]
struct ManifestCamera {
    index: usize,
    name: String,
    split: &'static str,
    /// width, height, fx, fy, cx, cy, world_to_camera: as in `render-ply`'s camera files.
    #[serde(flatten)]
    camera: CameraFile,
}

/// What the page reads first (`/scene.json`).
#[derive(Serialize)]
struct PlayerManifest {
    title: String,
    width: u32,
    height: u32,
    fps: f32,
    sh_degree: usize,
    /// Dataset frame indices, in order; frame i is at `/frames/<frames[i]>.ply`.
    frames: Vec<usize>,
    /// Bytes of the scene.acags file, when serving one.
    file_bytes: Option<usize>,
    cameras: Vec<ManifestCamera>,
    /// The camera the page starts at: the first test camera.
    start_camera: usize,
}

fn manifest(opened: &OpenedScene, sh_degree: usize) -> PlayerManifest {
    let scene = &opened.scene;
    let (width, height) = scene.resolution();
    PlayerManifest {
        title: opened.label.clone(),
        width,
        height,
        fps: crate::export::PLAYBACK_FPS,
        sh_degree,
        frames: scene.frames.frames().collect(),
        file_bytes: opened.file_bytes,
        cameras: scene
            .cameras
            .iter()
            .enumerate()
            .map(|(index, c)| ManifestCamera {
                index,
                name: c.name.clone(),
                split: scene.split_name(index),
                camera: CameraFile::from(&c.camera),
            })
            .collect(),
        start_camera: scene.test_cameras.first().copied().unwrap_or(0),
    }
}

/// A bound server with its scene.
pub struct PlayerServer {
    server: Server,
    opened: OpenedScene,
    sh_degree: usize,
    /// `/scene.json`'s bytes.
    manifest: Arc<Vec<u8>>,
    /// Decoded frames (PLY bytes), most recent last.
    cache: Vec<(usize, Arc<Vec<u8>>)>,
    address: SocketAddr,
    /// Host headers accepted (`None`: any, when bound to a non-loopback address on request).
    hosts: Option<Vec<String>>,
}

/// The Host headers a loopback server answers: its address and `localhost`, with its port. A
/// page from another site that rebinds its own name to 127.0.0.1 sends that name and is refused
/// (DNS rebinding), so only pages the user opened from this server read the scene.
fn loopback_hosts(address: SocketAddr) -> Vec<String> {
    let port = address.port();
    let mut hosts = vec![
        format!("localhost:{port}"),
        format!("127.0.0.1:{port}"),
        format!("[::1]:{port}"),
        address.to_string(),
    ];
    if port == 80 {
        hosts.extend(["localhost", "127.0.0.1", "[::1]"].map(String::from));
    }
    hosts
}

/// Binds `options.bind:options.port` for `opened`; a clear error when the port is taken.
pub fn bind(opened: OpenedScene, options: &ViewOptions) -> Result<PlayerServer> {
    crate::export::check_sh_degree(options.sh_degree)?;
    let wanted = SocketAddr::new(options.bind, options.port);
    let listener = std::net::TcpListener::bind(wanted).map_err(|e| match e.kind() {
        std::io::ErrorKind::AddrInUse => anyhow!(
            "port {} on {} is in use (another server?): give --port N, or --port 0 for any free port",
            options.port,
            options.bind
        ),
        _ => anyhow!("cannot listen on {wanted}: {e}"),
    })?;
    let address = listener.local_addr()?;
    let server = Server::from_listener(listener, None)
        .map_err(|e| anyhow!("cannot serve on {address}: {e}"))?;
    let manifest = Arc::new(
        serde_json::to_vec(&manifest(&opened, options.sh_degree)).expect("the manifest serialises"),
    );
    Ok(PlayerServer {
        server,
        opened,
        sh_degree: options.sh_degree,
        manifest,
        cache: Vec::new(),
        hosts: address.ip().is_loopback().then(|| loopback_hosts(address)),
        address,
    })
}

fn header(name: &str, value: &str) -> Header {
    Header::from_bytes(name.as_bytes(), value.as_bytes()).expect("ASCII header")
}

impl PlayerServer {
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// The page's address (an unspecified bind address shown as loopback).
    pub fn url(&self) -> String {
        let ip = match self.address.ip() {
            ip if ip.is_unspecified() => IpAddr::from([127, 0, 0, 1]),
            ip => ip,
        };
        format!("http://{}/", SocketAddr::new(ip, self.address.port()))
    }

    /// Answers requests until the process ends.
    pub fn serve(mut self) -> Result<()> {
        loop {
            let request = self.server.recv()?;
            if let Err(e) = self.answer(request) {
                eprintln!("view: {e:#}");
            }
        }
    }

    /// PLY bytes of dataset frame `frame`, decoded once.
    fn frame_bytes(&mut self, frame: usize) -> Result<Arc<Vec<u8>>> {
        if let Some(i) = self.cache.iter().position(|(f, _)| *f == frame) {
            let entry = self.cache.remove(i);
            let bytes = entry.1.clone();
            self.cache.push(entry);
            return Ok(bytes);
        }
        let (splats, _) = frame_splats(self.opened.export_source(), frame, self.sh_degree)?;
        let bytes = Arc::new(splat_ply_bytes(&splats));
        self.cache.push((frame, bytes.clone()));
        while self.cache.iter().map(|(_, b)| b.len()).sum::<usize>() > CACHE_BYTES
            && self.cache.len() > 1
        {
            self.cache.remove(0);
        }
        Ok(bytes)
    }

    fn answer(&mut self, request: Request) -> Result<()> {
        if !matches!(request.method(), Method::Get | Method::Head) {
            return Ok(request.respond(text(405, "only GET and HEAD"))?);
        }
        if let Some(hosts) = &self.hosts {
            let host = request
                .headers()
                .iter()
                .find(|h| h.field.equiv("Host"))
                .map(|h| h.value.as_str().to_ascii_lowercase());
            if !host.is_some_and(|h| hosts.contains(&h)) {
                return Ok(request.respond(text(403, "unknown Host header"))?);
            }
        }
        let (body, content_type): (Body, &str) = match route(request.url()) {
            Route::Page => (Body::Static(INDEX_HTML), "text/html; charset=utf-8"),
            Route::Script => (Body::Static(PLAYER_JS), "text/javascript; charset=utf-8"),
            Route::Manifest => (Body::Shared(self.manifest.clone()), "application/json"),
            Route::Frame(frame) => {
                if !self.opened.scene.frames.frames().contains(&frame) {
                    let message = format!(
                        "frame {frame} is outside the scene's GOP {:?}",
                        self.opened.scene.frames.frames()
                    );
                    return Ok(request.respond(text(404, &message))?);
                }
                match self.frame_bytes(frame) {
                    Ok(bytes) => (Body::Shared(bytes), "application/octet-stream"),
                    Err(e) => {
                        let message = format!("cannot decode frame {frame}: {e:#}");
                        eprintln!("view: {message}");
                        return Ok(request.respond(text(500, &message))?);
                    }
                }
            }
            Route::NotFound => return Ok(request.respond(text(404, "not found"))?),
        };
        // A Content-Length, not chunks: the page can show download progress.
        let length = body.as_ref().len();
        let response = Response::new(
            200.into(),
            Vec::new(),
            Cursor::new(body),
            Some(length),
            None,
        )
        .with_chunked_threshold(usize::MAX)
        .with_header(header("Content-Type", content_type))
        .with_header(header(
            "Content-Security-Policy",
            "default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'",
        ))
        .with_header(header("X-Content-Type-Options", "nosniff"))
        .with_header(header("Cache-Control", "no-store"));
        Ok(request.respond(response)?)
    }
}

/// A response body: an embedded asset or shared bytes (a cached frame is not copied).
enum Body {
    Static(&'static str),
    Shared(Arc<Vec<u8>>),
}

impl AsRef<[u8]> for Body {
    fn as_ref(&self) -> &[u8] {
        match self {
            Body::Static(s) => s.as_bytes(),
            Body::Shared(b) => b,
        }
    }
}

fn text(status: u16, message: &str) -> Response<Cursor<Vec<u8>>> {
    Response::from_string(message)
        .with_status_code(status)
        .with_header(header("Content-Type", "text/plain; charset=utf-8"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_four_kinds_of_path_exist() {
        assert_eq!(route("/"), Route::Page);
        assert_eq!(route("/?frame=3&camera=1"), Route::Page);
        assert_eq!(route("/index.html"), Route::Page);
        assert_eq!(route("/player.js"), Route::Script);
        assert_eq!(route("/scene.json"), Route::Manifest);
        assert_eq!(route("/frames/12.ply"), Route::Frame(12));
        assert_eq!(route("/frames/0.ply?x=1"), Route::Frame(0));
        for bad in [
            "/frames/../../etc/passwd",
            "/frames/..%2F..%2Fetc%2Fpasswd.ply",
            "/frames/-1.ply",
            "/frames/1.5.ply",
            "/frames/.ply",
            "/frames/99999999999999999999.ply",
            "/frames/3.ply/",
            "/etc/passwd",
            "/../Cargo.toml",
            "//scene.json",
            "/player.js/..",
            "",
        ] {
            assert_eq!(route(bad), Route::NotFound, "{bad}");
        }
    }
}
