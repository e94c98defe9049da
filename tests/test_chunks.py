import pytest
import torch

from psmini import ShapeError, _chunks
from psmini._chunks import CPU_CHUNK_ELEMENTS, batch_part, chunks


class TestChunks:
    def test_one_capture_at_a_time_on_the_cpu(self):
        """A capture of 8 × 400² observations fills a chunk; smaller items share one; the last is what is left."""
        assert chunks(torch.empty(3, 8, 400, 400)) == [slice(0, 1), slice(1, 2), slice(2, 3)]
        items_per_chunk = CPU_CHUNK_ELEMENTS // (8 * 100 * 100)
        assert chunks(torch.empty(2 * items_per_chunk + 1, 8, 100, 100)) == [
            slice(0, items_per_chunk), slice(items_per_chunk, 2 * items_per_chunk),
            slice(2 * items_per_chunk, 2 * items_per_chunk + 1)]

    def test_an_item_larger_than_a_chunk_is_one_chunk(self):
        assert chunks(torch.empty(2, 96, 512, 612)) == [slice(0, 1), slice(1, 2)]

    def test_devices_take_the_whole_batch(self):
        assert chunks(torch.empty(16, 8, 400, 400, device="meta")) == [slice(0, 16)]

    def test_empty_and_single_batches(self):
        assert chunks(torch.empty(0, 8, 4, 4)) == [slice(0, 0)]
        assert chunks(torch.empty(1, 8, 400, 400)) == [slice(0, 1)]

    def test_batch_part(self):
        images = torch.empty(4, 8, 5, 5)
        dark = torch.arange(4.0).view(4, 1, 1, 1).expand(4, 1, 5, 5)
        assert torch.equal(batch_part(dark, images, slice(1, 3), "dark")[:, 0, 0, 0], torch.tensor([1.0, 2.0]))
        card = torch.empty(1, 8, 5, 5)
        assert batch_part(card, images, slice(1, 3), "reference") is card  # broadcast over the batch
        stack = torch.empty(8, 5, 5)
        assert batch_part(stack, images, slice(1, 3), "reference") is stack
        assert batch_part(None, images, slice(1, 3), "mask") is None

    def test_batch_part_of_another_batch_raise(self):
        expected = r"dark must broadcast to the images' shape \(4, 8, 5, 5\).*\(3, 1, 5, 5\)"
        with pytest.raises(ShapeError, match=expected):
            batch_part(torch.empty(3, 1, 5, 5), torch.empty(4, 8, 5, 5), slice(0, 1), "dark")

    def test_constant_is_read_at_call_time(self, monkeypatch):
        """Tests shrink the chunk to exercise chunked paths on small images."""
        monkeypatch.setattr(_chunks, "CPU_CHUNK_ELEMENTS", 2 * 8 * 4 * 4)
        assert chunks(torch.empty(3, 8, 4, 4)) == [slice(0, 2), slice(2, 3)]
