import { defineConfig } from 'vite';

// The C++ server serves ../build/web (--web-root); relative URLs let it live under any path.
export default defineConfig({
  base: './',
  build: {
    outDir: '../build/web',
    emptyOutDir: true,
    chunkSizeWarningLimit: 1024, // three.js alone is ~0.6 MB minified; one chunk is intended
  },
  test: {
    include: ['src/**/*.test.js'],
    environment: 'node',
  },
});
