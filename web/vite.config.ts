import { defineConfig } from "vite";

declare const process: { env: Record<string, string | undefined> };

// The FastAPI server serves the bundle from server/servotune/web_dist at "/".
// `npm run dev` proxies the API and the websocket to a server on port 8000
// (`servotune demo`), so the client can be developed with hot reload.
const backend = process.env.SERVOTUNE_BACKEND ?? "http://127.0.0.1:8000";

export default defineConfig({
  base: "./",
  build: {
    outDir: "../server/servotune/web_dist",
    emptyOutDir: true,
    target: "es2022",
    chunkSizeWarningLimit: 300,
  },
  server: {
    port: 5173,
    proxy: {
      "/api": { target: backend, changeOrigin: true },
      "/ws": { target: backend, ws: true, changeOrigin: true },
    },
  },
});
